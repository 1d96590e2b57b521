"""The inference panel speaks the posterior (issue 61), in headless chromium against a real
``dejaview serve``: set a prior and a timed target in the panel, solve with samples by the default
search, and see the 90 % credible region on the floor, the intervals, the modes with their
probability (a click plays that past) and the sampler's agreement in words; the exported scene
holds the prior, the targets and the samples. Objects added in the browser (a box, a mesh of the
scene root) can be made the source or fixed. Screenshots: see ``artifacts`` in conftest."""

from __future__ import annotations

import pytest

from dejaview.scene.xml import read_scene_string

from .conftest import load_scene, needs_browser, open_viewer, state

pytestmark = needs_browser
SCENE = "scenes/toss.xml"


def change(page, selector: str, value: str) -> None:
    page.fill(selector, value)
    page.dispatch_event(selector, "change")


def test_prior_timed_target_samples_region_intervals_modes_export(page, web_server, web_root, artifacts):
    open_viewer(page, web_server)
    load_scene(page, SCENE)
    # the seed's optimiser settings live under "advanced", folded; the scene asks for adam
    assert not page.is_visible("#iterations") and page.is_visible("#prior-speed")
    page.click("#advanced summary")
    page.select_option("#optimizer", "auto")  # the default search: it draws samples
    page.click("#advanced summary")
    page.uncheck("#heatmap")
    page.dispatch_event("#heatmap", "change")

    change(page, "#prior-speed", "1.5")  # thrown gently, not hurled
    change(page, "#prior-spin", "")
    change(page, "#samples", "20")  # 40 particles: two sampler runs, so R-hat is checked
    page.click("#add-target")  # a <target time> halfway (0.1 s), between the set-up and the end
    s = state(page)
    assert [t["time"] for t in s["targets"]] == [None, pytest.approx(0.1)]
    assert s["targets"][1]["orientation"] is None and s["selected"] == "#target:1"
    change(page, "#targets tr[data-index='1'] input.time", "0.08")
    page.evaluate("window.dejaview.setPose('#target:1', [0.07, 0.02, 0.37])")  # where it was seen then
    s = state(page)
    assert s["belief"]["prior"] == {"speed": 1.5, "spin": None, "tilt": None} and s["belief"]["samples"] == 20
    assert s["targets"][1]["time"] == pytest.approx(0.08)
    assert s["targets"][1]["position"] == pytest.approx([0.07, 0.02, 0.37])
    assert [o["label"] for o in s["observations"]] == ["seen moving", "0.08 s"]
    page.screenshot(path=artifacts / "posterior-1-prior-and-timed-target.png")

    page.click("#run-solve")
    page.wait_for_function("window.dejaview.state().jobs.some(j => j.state === 'done' || j.state === 'failed')",
                           timeout=120_000)
    page.wait_for_function("(s => s.region && s.region.shown && s.samplesShown)(window.dejaview.state())",
                           timeout=30_000)
    s = state(page)
    assert [(j["kind"], j["state"]) for j in s["jobs"]] == [("solve", "done")], s["notifications"][-3:]
    post = s["result"]["posterior"]
    assert post["samples"] == 20 and post["sampler"]["runs"] == 2
    # the region holds 90 % of the samples' density, inside the start area
    region = s["region"]
    assert region["from"] == "samples" and 0.9 <= region["mass"] < 0.999 and region["cells"] > 0
    assert 0 < region["area"] < 0.2 * 0.2
    # an interval per free parameter, as result.json has them, with the median in the row
    assert [r["parameter"] for r in s["intervals"]] == list(post["intervals"])
    x = post["intervals"]["linear_velocity.x"]
    row = next(r["text"] for r in s["intervals"] if r["parameter"] == "linear_velocity.x")
    assert f"{x['median']:.3f}" in row or f"{x['median']:.2f}" in row, row
    # the modes with their probability, the agreement in words
    assert len(s["modes"]) == len(post["modes"]) >= 1
    assert s["modes"][0].startswith(f"1. {round(100 * post['modes'][0]['probability'])} %: from (")
    agree = post["agreement"]["runs_agree"]
    assert ("agree (R-hat at most" if agree else "disagree (R-hat up to") in s["agreement"], s["agreement"]
    page.eval_on_selector("#posterior-view", "e => e.scrollIntoView({block: 'end'})")
    page.screenshot(path=artifacts / "posterior-2-region-intervals-modes.png")

    # a click on a mode plays its past: a simulate job from its start; the solve's results stay
    page.click("#modes li:first-child button")
    page.wait_for_function("window.dejaview.state().jobs.filter(j => j.state === 'done').length === 2",
                           timeout=60_000)
    page.wait_for_function("window.dejaview.state().animation.playing")
    s = state(page)
    assert s["jobs"][1]["kind"] == "simulate" and s["modePlaying"] == 0
    assert s["region"]["shown"] and s["result"]["posterior"]["samples"] == 20 and s["intervals"]
    page.evaluate("window.dejaview.seek(0)")
    start = post["modes"][0]["initial_state"]["position"]
    assert state(page)["positions"]["cube"] == pytest.approx(start, abs=1e-4)
    page.eval_on_selector("#posterior-view", "e => e.scrollIntoView({block: 'end'})")
    page.screenshot(path=artifacts / "posterior-3-mode-played.png")

    # the export holds the prior, both targets and the samples, and no optimizer (the default search)
    xml = page.evaluate("window.dejaview.exportXml()")
    (artifacts / "posterior-exported.xml").write_text(xml)
    scene = read_scene_string(xml, base_dir=web_root / "scenes", filename="exported.xml")
    inf = scene.inference
    assert inf.prior.speed == 1.5 and inf.prior.spin is None and inf.posterior.samples == 20
    assert [t.time for t in inf.targets] == [None, pytest.approx(0.08)]
    assert inf.targets[1].position == pytest.approx((0.07, 0.02, 0.37)) and inf.targets[1].orientation is None
    assert inf.targets[0].moving is True and inf.optimizer == "auto" and inf.heatmap is None
    assert 'optimizer=' not in xml and "<!--" in xml


def test_belief_and_observations_round_trip_through_the_export(page, web_server, web_root):
    """Every belief input and the observations' table write exactly the spec's elements; clearing
    an input removes its attribute, and an element left empty goes."""
    open_viewer(page, web_server)
    load_scene(page, SCENE)
    page.click("#advanced summary")
    for selector, value in (("#prior-tilt", "0.05"), ("#obs-sigma", "0.01"), ("#obs-angle-sigma", "0.1"),
                            ("#obs-rest-speed", "0.03"), ("#phys-friction", "0.3"), ("#phys-stiffness", "0.5"),
                            ("#mu-restitution", "0.1"), ("#samples", "7"), ("#iterations", "")):
        change(page, selector, value)
    page.select_option("#targets tr[data-index='0'] select", "rest")  # the end: seen lying still
    page.click("#add-target")
    page.select_option("#targets tr[data-index='1'] select", "rest")  # lay still at its moment too
    page.click("#add-target")
    page.click("#targets tr[data-index='1'] button")  # and delete the first timed one
    page.check("#targets tr[data-index='1'] input.pose")  # the other saw a pose: the set-up orientation
    scene = read_scene_string(page.evaluate("window.dejaview.exportXml()"), base_dir=web_root / "scenes",
                              filename="exported.xml")
    inf = scene.inference
    assert (inf.prior.speed, inf.prior.tilt) == (None, 0.05)
    assert (inf.observation.sigma, inf.observation.angle_sigma, inf.observation.rest_speed) == (0.01, 0.1, 0.03)
    assert (inf.physics_prior.friction, inf.physics_prior.restitution, inf.physics_prior.stiffness) == (0.3, None, 0.5)
    assert inf.model_uncertainty.restitution == 0.1 and inf.posterior.samples == 7 and inf.iterations == 200
    assert [(t.time, t.moving) for t in inf.targets] == [(None, None), (pytest.approx(0.1), None)]
    assert inf.targets[0].orientation is None and inf.targets[1].orientation == pytest.approx((1, 0, 0, 0))
    for selector in ("#prior-tilt", "#phys-friction", "#phys-stiffness", "#mu-restitution", "#samples"):
        change(page, selector, "")
    xml = page.evaluate("window.dejaview.exportXml()")
    for gone in ("<prior", "<physics-prior", "<model-uncertainty", "<posterior"):
        assert gone not in xml, gone
    # a value the spec's reader refuses is refused here, and the scene keeps what it had
    change(page, "#obs-sigma", "-1")
    assert state(page)["belief"]["observation"]["sigma"] == 0.01
    assert any("positive" in n["text"] for n in state(page)["notifications"] if n["kind"] == "error")


def test_add_a_box_and_a_mesh_make_them_the_source_and_fixed(page, web_server, web_root, artifacts):
    open_viewer(page, web_server)
    load_scene(page, SCENE)
    assert page.eval_on_selector_all("#spawn-kind option", "os => os.map(o => o.value)") == [
        "box", "sphere", "cylinder", "mesh:examples/meshes/box.obj", "mesh:meshes/cube.obj"]
    page.select_option("#spawn-kind", "box")
    page.click("#spawn")
    page.wait_for_function("window.dejaview.state().meshesLoaded === 5")
    assert state(page)["selected"] == "box1" and state(page)["gizmoAttached"]
    page.evaluate("window.dejaview.setPose('box1', [0.25, -0.2, 0.3])")
    page.check("#objects tr[data-id='box1'] input[type=radio]")
    page.select_option("#spawn-kind", "mesh:meshes/cube.obj")
    page.click("#spawn")
    page.wait_for_function("window.dejaview.state().meshesLoaded === 6")
    page.check("#objects tr[data-id='cube1'] input[type=checkbox]")
    s = state(page)
    assert s["objects"][-2:] == ["box1", "cube1"] and s["source"] == "box1"
    assert s["setup"]["box1"] == pytest.approx([0.25, -0.2, 0.3])
    page.screenshot(path=artifacts / "spawned-box-source.png")

    scene = read_scene_string(page.evaluate("window.dejaview.exportXml()"), base_dir=web_root / "scenes",
                              filename="exported.xml", check_files=True)
    box = next(o for o in scene.objects if o.id == "box1")
    cube = next(o for o in scene.objects if o.id == "cube1")
    assert box.shape == "box" and box.size == pytest.approx((0.1, 0.1, 0.1)) and not box.fixed
    assert box.pose.position == pytest.approx((0.25, -0.2, 0.3)) and scene.inference.source == "box1"
    # the cube's start area (0.2 m wide, at 0.4 m) did not hold the box: it moved, its size kept
    area = scene.inference.start_area
    assert area.min == pytest.approx((0.15, -0.3, 0.3)) and area.max == pytest.approx((0.35, -0.1, 0.3))
    assert cube.fixed and cube.mesh.endswith("meshes/cube.obj") and cube.spheres.endswith("packings/cube.spheres")
    # removed again: gone from the table and the export
    page.evaluate("window.dejaview.select('cube1')")
    page.click("#remove-object")
    assert "cube1" not in state(page)["objects"] and 'id="cube1"' not in page.evaluate("window.dejaview.exportXml()")
