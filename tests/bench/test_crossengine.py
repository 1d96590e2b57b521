"""The cross-engine benchmark (``bench/crossengine.py``): MuJoCo observes, DejaView solves.

No timing assertions. The fidelity rows of the balls and the CLI's errors run in the default
suite; solving cases (seconds to a minute each) is ``slow``.
"""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.cli.bench import bench_module

pytest.importorskip("mujoco", reason="the crossengine bench re-simulates in MuJoCo (test extra: pip install -e '.[test]')")


@pytest.fixture(scope="module")
def crossengine():
    return bench_module("crossengine")


def _pitch_deg(q) -> float:
    """Degrees turned about +y (nose down for a box moving along +x) of the first body's
    orientation: a (4,) quaternion (w x y z) or (N, 4) rows."""
    import numpy as np

    w, _, y, _ = np.asarray(q, dtype=np.float64).reshape(-1, 4)[0]
    return float(np.degrees(2 * np.arctan2(y, w)))


def test_there_are_at_least_16_cases_of_every_kind(crossengine):
    names = [c.name for c in crossengine.CASES]
    assert len(names) >= 16 and len(set(names)) == len(names)
    for kind in ("ball", "box", "table", "floor", "slide", "bounce", "tumble"):
        assert any(kind in n for n in names), kind


@pytest.mark.parametrize("motion", ["bounce (ball dropped 0.5 m, e 0.3)", "bounce high", "roll", "slide to roll",
                                    "ball rolls off the table"])
def test_ball_motions_end_within_2_cm_of_mujoco(crossengine, motion):
    rows = crossengine.fidelity(print_fn=lambda *_: None, names=[motion], times=(1.0,))
    assert rows and all(r["gap_1s_m"] <= crossengine.FIDELITY_TOL for r in rows), rows


@pytest.mark.parametrize("motion", ["slide (box", "slide and spin", "tumble (box", "box lands on an edge",
                                    "box dropped nearly flat", "box thrown onto the floor", "box-box hit",
                                    "ball hits a resting box", "ball meets a box face"])
def test_box_motions_end_within_2_cm_of_mujoco(crossengine, motion):
    """The primitive box's mirror-symmetric packing (geometry/box_spheres.py) keeps these within
    1.1 cm (the mesh-lattice packing: 0.13, 1.33, 1.31, -, 0.74 cm); the box landing on an edge
    within 0.8 cm since the friction on the predicted slip (3.65 cm before); the ball hitting a
    resting box (ball-hits-box's start) within 0.5 cm, and 1 cm off the box's centre line within
    0.5 cm since a box body meets other bodies with its exact surface (7.3 cm before, against its
    packing's spheres). Since a box body meets the floor with its exact corners
    (``dejaview.sim.box_edges``): the box dropped 5 deg off flat within 0.03 cm (2.92 on its
    packing, whose face's spheres landed one after another), box-thrown within 1.34 cm (0.98 on
    the packing with the roll stick, 2.35 without); box-tumble-2's row (1.92 cm) is left out: where
    that box tips over an edge is decided by mm/s, and a machine's rounding moves it."""
    rows = crossengine.fidelity(print_fn=lambda *_: None, names=[motion], times=(1.0,))
    assert rows and all(r["gap_1s_m"] <= crossengine.FIDELITY_TOL for r in rows), rows
    if motion in ("slide (box", "slide and spin", "tumble (box", "box lands on an edge", "box dropped nearly flat",
                  "box-box hit"):
        # and they rest turned alike (0.0-0.7 deg apart; the spinning slide 15 deg apart in yaw on
        # the packing, 0.4 on the corners; the ball rows carry the ball's rolling)
        assert all(r["angle_1s_deg"] <= 3.0 for r in rows), rows


@pytest.mark.parametrize("along,length,edge,speed", [(0, 0.2, 0.4, 3.0), (1, 0.15, 0.3, 2.5)])
def test_a_box_tips_over_the_table_edge_as_a_rigid_box_does(crossengine, along, length, edge, speed):
    """DejaView tips the box sliding off the table, along its length (the fidelity row "box slides
    off the table") and across its width off the table's side, at the rate of a rigid flat box
    over a sharp edge (``bench/edge_tip.py``, a 2D reference sharing no code with the engines: 110
    and 142 deg/s). Since a static box's edges meet a box body's exact faces
    (``box_edges.static_edge_points``); before, the packing's face spheres (up to 5 cm in radius)
    met the table's edge on their curved sides and tipped the box early: across its width 2.5 deg
    ahead at 0.25 s (this test's bound is 2), 54.7 deg at 0.5 s against the rigid 49.7 (now 50.4;
    MuJoCo 51.4)."""
    import math

    reference = bench_module("edge_tip").tip(dt=1e-5, length=length, edge=edge, speed=speed)
    velocity = (speed, 0, 0) if along == 0 else (0, speed, 0)  # the first: the row "box slides off the table"
    objects = crossengine.box("box", (0.0, 0, crossengine.TABLE_TOP + crossengine.BOX[2] / 2), velocity)
    scene = crossengine.make_scene(crossengine.scene_text(objects, 0.35))
    times = (0.25, 0.3, 0.35)
    ours = crossengine.dejaview_run(scene, times)

    def tilt(q):  # nose down about +y along x; about -x along y
        return math.degrees(2 * math.atan2(q[0, 2] if along == 0 else -q[0, 1], q[0, 0]))

    pitch = {t: tilt(ours[t][1]) for t in times}
    for t in times:
        assert pitch[t] == pytest.approx(reference[t][2], abs=2.0), (t, pitch[t], reference[t])
        assert ours[t][0][0, along] == pytest.approx(reference[t][0], abs=0.01)
    rate = (pitch[0.35] - pitch[0.25]) / 0.1
    assert rate == pytest.approx(reference[0.35][3], rel=0.1)


def test_mujoco_tips_the_box_over_the_edge_as_a_rigid_box_does(crossengine):
    """MuJoCo tips the box sliding off the table at the rigid reference's rate (``bench/edge_tip.py``,
    110 deg/s) in the median over its steps of 10, 5 and 2 us (97, 119 and 113 deg/s), where at the
    export's 0.5 ms it tipped it at 240 deg/s (docs/physics-fidelity.md): a box sliding over a sharp
    edge at 2.3 m/s is the one motion here whose tipping still moves with MuJoCo's step."""
    import numpy as np

    reference = bench_module("edge_tip").tip(dt=1e-5)
    (name, objects, e) = [f for f in crossengine.FIDELITY if f[0] == "box slides off the table"][0]
    scene = crossengine.make_scene(crossengine.scene_text(objects, 0.35, restitution=e))
    pitches, rates = [], []
    for step in (1e-5, 5e-6, 2e-6):
        theirs = crossengine.mujoco_run(scene, (0.25, 0.35), timestep=step)
        pitch = {t: _pitch_deg(q) for t, (_, q) in theirs.items()}
        pitches.append(pitch[0.35])
        rates.append((pitch[0.35] - pitch[0.25]) / 0.1)
    assert float(np.median(pitches)) == pytest.approx(reference[0.35][2], abs=2.0), pitches
    assert float(np.median(rates)) == pytest.approx(reference[0.35][3], rel=0.1), rates


@pytest.mark.parametrize("pitch, velocity, pitch_rate", [(40.0, (2.2, -3.6), 110.0), (50.0, (2.0, -3.0), 172.0)])
def test_a_box_landing_on_its_edge_turns_on_as_a_rigid_box_does_in_both_engines(crossengine, pitch, velocity,
                                                                                pitch_rate):
    """A box landing on its front edge nose down (the first: how the box sliding off the table
    lands) leaves the floor turning on at 84 and 440 deg/s in a rigid impact with Coulomb friction
    (``bench/edge_tip.edge_impact``; the edge sticks). DejaView at the box body's 4 substeps 101
    and 502, converged in its step (91 / 90 and 495 / 501 at 8 / 16 substeps; 85 and 468 at 2,
    nearer the rigid turn by under-resolving the impact): a penalty impact lasts and turns the box
    while it lasts, 14 % more here, so DejaView is held to 15 %; MuJoCo 72 and 463 (99
    and 476 with the exported friction damped at 4 omega_0), and with it damped at the contact
    frequency alone (``mjcf.FRICTION_DAMPING`` 1 instead of 2) -6 and 402: too little friction
    during the impact, and the normal impulse, ahead of the centre of mass, stopped the turn."""
    import math

    rigid = bench_module("edge_tip").edge_impact(pitch, velocity, pitch_rate)
    th = math.radians(pitch)
    length, _, height = crossengine.BOX
    lowest = math.sin(th) * length / 2 + math.cos(th) * height / 2  # the front-bottom edge below the centre
    box = crossengine.box("box", (3.0, 0.0, lowest + 0.0005), (velocity[0], 0, velocity[1]),
                          (0, math.radians(pitch_rate), 0), crossengine.about((0, 1, 0), pitch))
    scene = crossengine.make_scene(crossengine.scene_text(box, 0.05))
    t0, t1 = 0.036, 0.04  # the impact is over by 15 ms, the box in flight until 45 ms (2 ms records)
    for run, rel in ((crossengine.dejaview_run, 0.15), (crossengine.mujoco_run, 0.1)):
        out = run(scene, (t0, t1))
        rate = (_pitch_deg(out[t1][1]) - _pitch_deg(out[t0][1])) / (t1 - t0)
        assert rate == pytest.approx(rigid[2], abs=max(25.0, rel * abs(rigid[2]))), (run.__name__, rate, rigid)


def test_mujoco_is_converged_at_the_benchs_step_where_the_exports_step_is_not(crossengine):
    """box-tumble-2's true start (a box bouncing over its corners, four impacts in 0.6 s): at the
    export's default step (``mjcf.MJ_TIMESTEP``, 0.5 ms) MuJoCo's end at 1.0 s is 4.3 cm from its
    run at 2 us, at ``MUJOCO_TIMESTEP`` (5 us) 0.2 mm: the bench's reference is converged on a
    tumbling box where a coarser step is not."""
    rows = crossengine.timestep_study(print_fn=lambda *_: None, steps=(5e-4, crossengine.MUJOCO_TIMESTEP),
                                      substeps=(), names=["case box-tumble-2"])
    at = f"gap_{1e3 * crossengine.MUJOCO_TIMESTEP:g}ms_m"
    assert len(rows) == 1 and rows[0][at] < 0.003, rows
    assert rows[0]["gap_0.5ms_m"] > 0.02, rows


@pytest.mark.slow
def test_mujoco_is_converged_at_the_benchs_step(crossengine):
    """At ``MUJOCO_TIMESTEP`` MuJoCo's end is within 3 mm of its run at 2 us on every fidelity row
    (1.0 s) and every inference case's true start (the observation) but the box sliding off the
    table, as a row and as the case box-off-table (1.2 s): the reference is converged. Those two
    land on the box's front edge, close to where MuJoCo's box stops turning (72 deg/s after the
    impact where a rigid box turns on at 84), and either tip onto its end or fall back: at 5, 2,
    1 and 0.5 us the row ends at x = 1.372, 1.201, 1.342 and 1.281 m, 17 and 26 cm between 5 and
    2 us (docs/physics-fidelity.md, "The friction's damping at 2 omega_0"), a knife-edge in
    MuJoCo itself that no step resolves."""
    rows = crossengine.timestep_study(print_fn=lambda *_: None, steps=(crossengine.MUJOCO_TIMESTEP,),
                                      substeps=())
    at = f"gap_{1e3 * crossengine.MUJOCO_TIMESTEP:g}ms_m"
    assert len(rows) == len(crossengine.FIDELITY) + len(crossengine.CASES)
    knife = {"box slides off the table", "case box-off-table"}
    assert all(r[at] < 0.003 for r in rows if r["motion"] not in knife), rows


def test_the_solve_is_given_the_end_and_not_the_truth(crossengine):
    """The scene a case is solved from holds the observed end, the start area and the cases' prior;
    its source starts at the area's centre at rest (upright where the orientation is free), not at
    the truth: the scene's start seeds the search."""
    import numpy as np

    for case in crossengine.CASES:
        truth = crossengine.case_scene(case).object("source")
        for prior in (True, False):
            scene = crossengine.case_scene(case, ((0, 0, 0.75), (1, 0, 0, 0)), (0.2, 0.2), seed=0, prior=prior)
            source = scene.object("source")
            lo, hi = (np.asarray(v) for v in case.area)
            np.testing.assert_allclose(source.pose.position, (lo + hi) / 2)
            assert source.velocity.linear == (0, 0, 0) and source.velocity.angular == (0, 0, 0), case.name
            assert source.pose.orientation == ((1, 0, 0, 0) if case.orientation else truth.pose.orientation)
            assert any(truth.velocity.linear), case.name  # so the checks above can fail
            ball = truth.shape == "sphere"
            got = scene.inference.prior
            if not prior:
                assert got is None or (got.speed, got.spin, got.tilt) == (None, None, None), case.name
            else:
                assert got.speed == 2.0 and (got.spin is None) == ball and got.tilt is None, (case.name, got)
            # the other objects (a resting box) keep their start
            assert [o.pose for o in scene.objects if o.id != "source"] == \
                [o.pose for o in crossengine.case_scene(case).objects if o.id != "source"]


def test_an_area_offset_moves_the_floor_cases_areas_off_the_truth(crossengine, monkeypatch):
    """``offset_area``: a floor case's area (centred on the truth's x, y) moves by the offset and
    still holds the truth, so the guess at its centre is not the truth's position; a table case's
    area (the table top, also where the truth starts at its centre) stays; an offset that would
    leave the truth outside is an error; ``run`` solves the moved cases and writes the offset into
    the rows."""
    import numpy as np

    moved = 0
    for case in crossengine.CASES:
        shifted = crossengine.offset_area(case, (0.15, -0.1))
        truth = np.asarray(crossengine.case_scene(case).object("source").pose.position)
        lo, hi = (np.asarray(v) for v in case.area)
        new_lo, new_hi = (np.asarray(v) for v in shifted.area)
        assert np.all(new_lo <= truth + 1e-9) and np.all(truth <= new_hi + 1e-9), case.name
        if not np.allclose((lo[:2], hi[:2]), crossengine.TABLE_AREA):
            moved += 1
            np.testing.assert_allclose(new_lo - lo, (0.15, -0.1, 0))
            np.testing.assert_allclose(new_hi - hi, (0.15, -0.1, 0))
            guess = crossengine.case_scene(shifted, ((0, 0, 0.75), (1, 0, 0, 0))).object("source").pose.position
            assert np.linalg.norm(np.asarray(guess)[:2] - truth[:2]) > 0.17, case.name
        else:
            assert shifted == case, case.name
        assert crossengine.offset_area(case) == case
    assert moved == sum("table" not in c.name for c in crossengine.CASES)  # every floor case
    (floor,) = [c for c in crossengine.CASES if c.name == "ball-slide-floor"]
    with pytest.raises(ValueError, match="area offset 0.35 0 m moves case ball-slide-floor's start area off"):
        crossengine.offset_area(floor, (0.35, 0.0))
    seen = []
    monkeypatch.setattr(crossengine, "solve_case", lambda case, *a, **k: seen.append(case) or {
        "section": "inference", "case": case.name, "seed": 0, "model_uncertainty": "off", "seconds": 1.0,
        "success": True})
    rows = crossengine.run(print_fn=lambda *_: None, cases=("ball-slide-floor",), warp=False, with_fidelity=False,
                           baseline=False, area_offset=(0.1, 0.05))
    assert seen[0].area == crossengine.offset_area(floor, (0.1, 0.05)).area != floor.area
    assert rows[0]["area_offset"] == "0.1 0.05"


def test_random_throws_are_seeded_and_land_on_the_floor_clear_of_the_table(crossengine):
    """``throws``' boxes: the same seed draws the same starts, another seed others, and every start
    lies in ``THROW_AREA`` with the whole box above the floor and clear of the table (half width
    0.4 m), so the first contact is the floor's."""
    import numpy as np

    def draw(seed):
        rng = np.random.default_rng(seed)
        return [crossengine.random_throw(rng) for _ in range(50)]

    a, b, c = draw(3), draw(3), draw(4)
    assert all(np.array_equal(x["position"], y["position"]) and np.array_equal(x["angular"], y["angular"])
               for x, y in zip(a, b))
    assert not np.allclose([x["position"] for x in a], [x["position"] for x in c])
    half_diagonal = float(np.linalg.norm(crossengine.BOX)) / 2
    lo, hi = (np.asarray(v) for v in crossengine.THROW_AREA)
    for x in a:
        p = x["position"]
        assert np.all(p >= lo) and np.all(p <= hi), p
        assert p[2] - half_diagonal > 0 and p[0] - half_diagonal > 0.4, p
        assert abs(np.linalg.norm(x["orientation"]) - 1) < 1e-12


def test_random_cases_are_seeded_tumbling_boxes_clear_of_the_floor_and_the_table(crossengine):
    """``random_cases``: the same seed draws the same cases, another seed others; each is a box whose
    true start lies in ``RANDOM_AREA`` and in its own start area, tilted at most ``RANDOM_TILT``,
    the whole box above the floor and clear of the table, its orientation free."""
    import numpy as np

    def starts(cases):
        out = []
        for case in cases:
            scene = crossengine.case_scene(case)
            (source,) = [o for o in scene.objects if o.id == "source"]
            out.append((np.asarray(source.pose.position), np.asarray(source.pose.orientation), case))
        return out

    a, b, c = crossengine.random_cases(20, 5), crossengine.random_cases(20, 5), crossengine.random_cases(20, 6)
    assert a == b and a != c
    assert [x.name for x in a] == [f"box-random-5-{i}" for i in range(20)]
    half_diagonal = float(np.linalg.norm(crossengine.BOX)) / 2
    lo, hi = (np.asarray(v) for v in crossengine.RANDOM_AREA)
    tilts = []
    for p, q, case in starts(a):
        assert np.all(p >= lo) and np.all(p <= hi), p
        assert np.all(p >= case.area[0]) and np.all(p <= case.area[1]), (p, case.area)
        assert p[2] - half_diagonal > 0 and p[0] - half_diagonal > 0.4, p
        assert case.orientation and not case.ball
        w, x, y, z = q / np.linalg.norm(q)
        tilts.append(np.degrees(np.arccos(np.clip(1 - 2 * (x * x + y * y), -1, 1))))  # body z against world z
    assert max(tilts) <= crossengine.RANDOM_TILT + 1e-9 and max(tilts) > 20, tilts
    assert crossengine.random_cases(0) == ()
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="random cases"):
            crossengine.random_cases(bad)


def test_perturbed_cases_are_the_cases_kinds_moved_scaled_and_turned_within_their_bounds(crossengine):
    """``perturbed_cases``: seeded (per case, whichever others are chosen); each keeps its case's kind
    (ball or box, what is free, the duration, the restitution, the other objects); the start moved
    at most ``PERTURB_SHIFT`` per axis (not in height where the height is given), inside its start area,
    a floor case's area centred on it, a table case's the table top; every velocity component scaled
    by 1 -/+ ``PERTURB_SCALE`` (zeros stay zero); the orientation turned at most ``PERTURB_TURN`` (a given
    one about the vertical only); the source clear of the floor."""
    import numpy as np

    ce = crossengine
    a, b, c = ce.perturbed_cases(3), ce.perturbed_cases(3), ce.perturbed_cases(4)
    assert a == b and a != c
    assert [x.name for x in a] == [f"{x.name}-p3" for x in ce.CASES]
    subset = tuple(x for x in ce.CASES if x.name in ("box-thrown", "ball-bounce"))
    assert ce.perturbed_cases(3, subset) == tuple(x for x in a if x.name in ("box-thrown-p3", "ball-bounce-p3"))
    moved = []
    for seed in range(4):
        for case, new in zip(ce.CASES, ce.perturbed_cases(seed)):
            assert (new.ball, new.orientation, new.duration, new.restitution) == \
                (case.ball, case.orientation, case.duration, case.restitution)
            assert new.objects.split("</object>", 1)[1] == case.objects.split("</object>", 1)[1]
            s0, s1 = ce.case_scene(case).object("source"), ce.case_scene(new).object("source")
            p0, p1 = np.asarray(s0.pose.position), np.asarray(s1.pose.position)
            lo, hi = (np.asarray(v) for v in new.area)
            assert np.all(np.abs(p1 - p0) <= ce.PERTURB_SHIFT + 1e-12), (new.name, p1 - p0)
            assert np.all(p1 >= lo - 1e-12) and np.all(p1 <= hi + 1e-12), (new.name, p1, new.area)
            if case.area[0][2] == case.area[1][2]:
                assert p1[2] == p0[2], new.name
            if np.allclose((case.area[0][:2], case.area[1][:2]), ce.TABLE_AREA):
                assert new.area == case.area, new.name
            else:
                assert np.allclose((lo + hi) / 2 - p1, (np.asarray(case.area[0]) + case.area[1]) / 2 - p0), new.name
            for v0, v1 in ((s0.velocity.linear, s1.velocity.linear), (s0.velocity.angular, s1.velocity.angular)):
                v0, v1 = np.asarray(v0), np.asarray(v1)
                assert np.all((v0 == 0) == (v1 == 0)), (new.name, v0, v1)
                ratio = v1[v0 != 0] / v0[v0 != 0]
                assert np.all(np.abs(ratio - 1) <= ce.PERTURB_SCALE + 1e-9), (new.name, ratio)
            turn = ce.angle_deg(s0.pose.orientation, s1.pose.orientation)
            assert turn <= ce.PERTURB_TURN + 1e-6, (new.name, turn)
            w, x, y, z = s1.pose.orientation
            up = 1 - 2 * (x * x + y * y)  # body z against world z
            if not case.ball and not case.orientation:
                assert up > 1 - 1e-9, (new.name, s1.pose.orientation)
            if case.ball:
                assert p1[2] - ce.BALL_R >= -1e-9, new.name
            else:
                rz = np.array([2 * (x * z - w * y), 2 * (y * z + w * x), up])
                assert p1[2] - float(np.abs(rz) @ np.asarray(ce.BOX)) / 2 >= -1e-9, new.name
            moved.append((np.abs(p1 - p0).max(), turn))
    assert max(m for m, _ in moved) > 0.03 and max(t for _, t in moved) > 8, moved
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="seeds"):
            ce.perturbed_cases(bad)


def _solved_rows(tmp_path, *args) -> list[dict]:
    """The inference rows (CSV dicts) of ``dejaview bench crossengine ARGS`` with model uncertainty only,
    without the fidelity table or Warp."""
    import csv

    out = tmp_path / "rows.csv"
    result = CliRunner().invoke(cli, ["bench", "crossengine", *args, "--no-fidelity", "--no-baseline", "--no-warp",
                                      "--csv", str(out)])
    assert result.exit_code == 0, result.output
    return [r for r in csv.DictReader(out.open()) if r["section"] == "inference"]


@pytest.mark.slow
def test_cli_random_cases_are_solved_alone_unless_cases_are_named(tmp_path):
    """``--random-cases 1`` solves one random box and none of the cases; with ``--cases`` both."""
    rows = _solved_rows(tmp_path, "--random-cases", "1", "--random-seed", "3")
    assert [r["case"] for r in rows] == ["box-random-3-0"], rows
    rows = _solved_rows(tmp_path, "--random-cases", "1", "--cases", "ball-on-table")
    assert [r["case"] for r in rows] == ["ball-on-table", "box-random-0-0"], rows


@pytest.mark.slow
def test_cli_perturbed_seed_solves_the_named_cases_perturbed(tmp_path):
    """``--perturbed-seed 2 --cases ball-slide-floor`` solves that case perturbed, under its new name,
    and solves it (a ball sliding on the floor is solved by every seed in every setting)."""
    rows = _solved_rows(tmp_path, "--perturbed-seed", "2", "--cases", "ball-slide-floor")
    assert [r["case"] for r in rows] == ["ball-slide-floor-p2"], rows
    assert rows[0]["success"] == "True", rows


def test_cli_throws_measures_the_engines_gap_and_its_controls(tmp_path):
    """One throw through ``dejaview bench crossengine --throws``: its row has the gap at both times
    and the three controls; MuJoCo at half its step ends within 5 mm of itself (the reference is
    converged on a tumbling box too: 0.4 mm on this throw, 3.4 cm between the engines)."""
    import csv

    out = tmp_path / "throws.csv"
    result = CliRunner().invoke(cli, ["bench", "crossengine", "--throws", "1", "--seeds", "2", "--csv", str(out)])
    assert result.exit_code == 0, result.output
    assert "1 random box throws (seed 2)" in result.output, result.output
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 1 and rows[0]["section"] == "throws", rows
    for key in ("gap_0.5s_m", "gap_1s_m", "mujoco_nudged_m", "dejaview_nudged_m", "dejaview_4x_substeps_m"):
        assert 0 <= float(rows[0][key]) < 10, (key, rows)
    assert 0 <= float(rows[0]["angle_1s_deg"]) <= 180, rows
    assert float(rows[0]["mujoco_half_step_m"]) < 0.005, rows


def test_an_area_offset_off_the_truth_is_a_one_line_error():
    result = CliRunner().invoke(cli, ["bench", "crossengine", "--cases", "ball-slide-floor", "--no-fidelity",
                                      "--area-offset", "0", "0.4"])
    assert result.exit_code != 0 and "--area-offset" in result.output, result.output
    assert "moves case ball-slide-floor's start area off its true start" in result.output, result.output


def test_unknown_cases_are_a_one_line_error():
    result = CliRunner().invoke(cli, ["bench", "crossengine", "--cases", "nope", "--no-fidelity"])
    assert result.exit_code != 0 and "unknown case(s) nope" in result.output


def test_bad_seeds_are_a_one_line_error():
    for bad, says in (("x", "not a comma-separated list"), ("-1", "whole numbers >= 0")):
        for mode in (["--no-fidelity"], ["--throws", "1"]):
            result = CliRunner().invoke(cli, ["bench", "crossengine", "--seeds", bad, *mode])
            assert result.exit_code != 0 and says in result.output and "--seeds" in result.output, result.output


@pytest.mark.slow  # two solves, 31 s; the bench solves in the default run: test_cli_flat_prior_solves_without_the_cases_prior
def test_each_seed_solves_each_case_once_and_the_summary_pools_them(crossengine):
    """``--seeds 0,1``: one solve per seed (the scene's ``<inference seed>``), the same observation,
    and the summary counts all of them and says which cases every seed solved."""
    lines = []
    rows = crossengine.run(print_fn=lines.append, cases=("ball-on-table",), warp=False, with_fidelity=False,
                           baseline=False, seeds=(0, 1))
    assert [(r["case"], r["seed"]) for r in rows] == [("ball-on-table", 0), ("ball-on-table", 1)]
    assert {r["prior"] for r in rows} == {crossengine.PRIOR["ball"]}
    ok = sum(r["success"] for r in rows)
    assert any(f"MuJoCo {ok}/2 within 3 cm" in line for line in lines), lines
    assert any("over 2 seeds, cases solved by every seed:" in line for line in lines), lines
    (case,) = [c for c in crossengine.CASES if c.name == "ball-on-table"]
    assert crossengine.case_scene(case, ((0, 0, 0.75), (1, 0, 0, 0)), None, seed=1).inference.seed == 1


def test_cli_flat_prior_solves_without_the_cases_prior(tmp_path):
    out = tmp_path / "rows.csv"
    result = CliRunner().invoke(cli, ["bench", "crossengine", "--cases", "ball-on-table", "--no-fidelity",
                                      "--no-baseline", "--no-warp", "--flat-prior", "--csv", str(out)])
    assert result.exit_code == 0, result.output
    assert "MuJoCo 1/1 within 3 cm" in result.output or "MuJoCo 0/1 within 3 cm" in result.output
    import csv

    (row,) = [r for r in csv.DictReader(out.open()) if r["section"] == "inference"]
    assert row["prior"] == "flat"


@pytest.mark.slow
@pytest.mark.parametrize("case", ["ball-bounce-table", "box-slide-spin-floor"])
def test_answers_with_model_uncertainty_end_within_3_cm_in_mujoco(crossengine, case):
    """Two cases whose answers without model uncertainty measured 8.1 and 5.3 cm off in MuJoCo
    (needle pasts; box-slide-spin-floor 0.7 cm with the symmetric box packing); with it 0.38 and
    0.12 cm. With MuJoCo at 50 us (2026-11-25): 5.6 and 0.5 cm without, 2.7 and 2.3 cm with it,
    close to the bar (docs/physics-fidelity.md). Solved from the start area's centre under the
    cases' prior (2026-11-27): 0.52 and 0.10 cm with it (1.02 and 0.22 without)."""
    (c,) = [c for c in crossengine.CASES if c.name == case]
    row = crossengine.solve_case(c, crossengine.UNCERTAINTY, warp=False, print_fn=lambda *_: None)
    assert row["success"], row


def test_mujoco_at_its_default_contact_observes_a_case_at_the_scenes_step(crossengine):
    """``--engines mujoco-default``: MuJoCo at its own default contact (the world issue 58's hidden
    cases are observed in) at the scene's 2 ms step; a ball rolling on the table ends where it does
    in DejaView (rolling: contact-free but for friction), a ball dropped does not rebound there as
    it does in DejaView (the default contact is critically damped), and the bench's path solves a
    case in it."""
    import numpy as np

    engines = bench_module("crossengine_engines")
    cases = bench_module("crossengine_cases")
    scene = cases.make_scene(cases.scene_text(cases.ball("source", (1.0, 0.0, 0.5)), 0.6, restitution=0.6))
    times = (0.28, 0.6)  # just before the drop's impact (0.30 s), and after the rebound's apex (0.48 s)
    ours = engines.dejaview_run(scene, times)
    theirs = engines.mujoco_default_run(scene, times)
    assert ours[0.6][0][0][2] > 0.05 + 0.25 * 0.36 * 0.45  # DejaView: e = 0.6 rebounds 0.36 h
    assert theirs[0.6][0][0][2] < 0.06  # MuJoCo's default contact: hardly at all
    lines = []
    rows = crossengine.run(print_fn=lines.append, cases=("ball-on-table",), warp=False, with_fidelity=False,
                           baseline=False, engines=("mujoco-default",))
    assert [(r["engine"], r["model_uncertainty"]) for r in rows] == [("mujoco-default", "0.2 0.2")]
    assert 0 <= rows[0]["mujoco-default_end_error_m"] < 0.03, rows
    assert any("MJdflt" in line and "within 3 cm" in line for line in lines), lines
    assert np.isfinite(theirs[0.28][0]).all()


def test_the_fidelity_table_shows_mujoco_at_its_default_contact_without_holding_it_to_the_bar(crossengine):
    """``--engines mujoco-default`` adds its column to the fidelity table (``fidelity_engines``); the
    2 cm bar at 1.0 s reads the mapped MuJoCo and Bullet only: a ball dropped with e 0.7 rebounds in
    DejaView and the mapped MuJoCo, hardly at all at MuJoCo's default contact, and stays within the bar."""
    fid = bench_module("crossengine_fidelity")
    assert fid.fidelity_engines(("mujoco",)) == ("mujoco", "bullet")
    assert fid.fidelity_engines(("bullet", "mujoco-default")) == ("mujoco", "bullet", "mujoco-default")
    lines = []
    rows = crossengine.fidelity(print_fn=lines.append, names=["bounce high"], times=(1.0,),
                                engines=("mujoco", "mujoco-default"))
    (row,) = rows
    assert row["gap_1s_m"] <= crossengine.FIDELITY_TOL < row["mujoco_default_gap_1s_m"], row
    assert row["within_2cm_at_1s"] is True
    assert "md 1s" in lines[0]
