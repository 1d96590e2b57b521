"""End to end in headless chromium against a real ``dejaview serve``: load a scene, move the
source with the gizmo (real mouse input), solve with a heatmap, watch the trajectory animate and
the heatmap appear, export the edited scene. Screenshots: see ``artifacts`` in conftest."""

from __future__ import annotations

import math

import pytest

from dejaview.scene.xml import read_scene_string

from .conftest import load_scene, needs_browser, open_viewer, state

pytestmark = needs_browser
SCENE = "scenes/toss.xml"


def drag_gizmo_x(page, object_id: str, metres: float) -> None:
    """Grab the translate gizmo's x arrow with the mouse and drag it by about ``metres``."""
    origin = page.evaluate(f"window.dejaview.screenPoint({object_id!r})")
    ahead = page.evaluate(f"window.dejaview.screenPoint({object_id!r}, [0.1, 0, 0])")
    dx, dy = ahead["x"] - origin["x"], ahead["y"] - origin["y"]  # pixels per 10 cm along x
    norm = math.hypot(dx, dy)
    for step in range(4, 40):  # walk out along the arrow until the gizmo highlights its x axis
        x, y = origin["x"] + dx / norm * step * 3, origin["y"] + dy / norm * step * 3
        page.mouse.move(x, y)
        if page.evaluate("window.dejaview.three.gizmo.axis") == "X":
            break
    else:
        raise AssertionError("the gizmo's x arrow was not found under the mouse")
    page.mouse.down()
    for k in range(1, 11):
        page.mouse.move(x + dx * 10 * metres * k / 10, y + dy * 10 * metres * k / 10)
    page.mouse.up()


def test_load_move_solve_animate_heatmap_export(page, web_server, web_root, artifacts):
    open_viewer(page, web_server)
    loaded = load_scene(page, SCENE)
    assert loaded["objects"] == ["floor", "table", "cube", "ball"] and loaded["source"] == "cube"
    assert loaded["positions"]["cube"] == pytest.approx([0, 0, 0.4])
    page.screenshot(path=artifacts / "1-loaded.png")

    # click the cube on the canvas: it is selected and gets the gizmo
    at = page.evaluate("window.dejaview.screenPoint('cube')")
    page.mouse.click(at["x"], at["y"])
    assert state(page)["selected"] == "cube" and state(page)["gizmoAttached"]
    drag_gizmo_x(page, "cube", 0.05)
    moved = state(page)["setup"]["cube"]
    assert 0.01 < moved[0] < 0.15 and moved[1:] == pytest.approx([0, 0.4], abs=1e-6), moved
    page.screenshot(path=artifacts / "2-moved.png")

    # inference settings through the panel: the seed's optimiser settings under "advanced"
    page.click("#advanced summary")
    page.fill("#iterations", "3")
    page.select_option("#optimizer", "adam")
    page.select_option("#gradient", "reverse")
    page.check("#heatmap")
    page.fill("#cells-x", "2")
    page.fill("#cells-y", "2")
    page.dispatch_event("#cells-y", "change")
    assert state(page)["settings"] == {"iterations": 3, "optimizer": "adam", "gradient": "reverse",
                                       "heatmap": True, "cells": [2, 2]}

    page.click("#run-solve")  # with the heatmap ticked: a heatmap job (which also returns the best trajectory)
    page.wait_for_function("window.dejaview.state().jobs.some(j => j.state === 'done' || j.state === 'failed')",
                           timeout=240_000)
    s = state(page)
    assert [j["state"] for j in s["jobs"]] == ["done"], (s["jobs"], s["notifications"][-3:])
    assert s["jobs"][0]["kind"] == "heatmap"
    assert s["loss"], "no progress reached the loss chart"
    kinds = [n["kind"] for n in s["notifications"]]
    assert "error" not in kinds, s["notifications"]
    assert s["trajectoryShown"] and {"cube", "ball"} <= set(s["trajectoryObjects"])
    assert s["heatmapShown"] and s["heatmapCells"] == [2, 2]
    # the 90 % credible region from the heatmap's cells: the most probable of the 4 until 90 %
    probability = sorted((p for row in s["live"]["probability"] for p in row), reverse=True)
    need = next(k for k in range(1, 5) if sum(probability[:k]) >= 0.9 * sum(probability) - 1e-12)
    assert s["region"]["shown"] and s["region"]["from"] == "heatmap" and s["region"]["cells"] == need
    assert s["region"]["mass"] == pytest.approx(sum(probability[:need]) / sum(probability))
    assert s["result"]["source"] == "cube"
    # the heatmap is the posterior's marginal: its samples' start points are drawn as a cloud
    # with a few of them re-simulated as faint trajectories
    page.wait_for_function("window.dejaview.state().samplesShown && window.dejaview.state().samplePaths > 0",
                           timeout=30_000)
    s = state(page)
    assert s["sampleCount"] == s["result"]["posterior"]["samples"] > 0
    assert 1 <= s["samplePaths"] <= 8
    page.screenshot(path=artifacts / "3a-posterior-samples.png")
    page.uncheck("#show-samples")
    assert not state(page)["samplesShown"] and state(page)["samplePaths"] == 0
    page.check("#show-samples")

    # the trajectory animates in real time: time advances and the cube moves along it
    page.wait_for_function("window.dejaview.state().animation.time > 0.05")
    a = state(page)
    page.wait_for_function(f"window.dejaview.state().positions.cube[2] != {a['positions']['cube'][2]}")
    b = state(page)
    assert b["animation"]["playing"] and b["animation"]["time"] != a["animation"]["time"]
    page.screenshot(path=artifacts / "3-solved-playing.png")

    # pause and scrub: the cube sits at the trajectory's pose at that time
    page.click("#play")
    assert not state(page)["animation"]["playing"]
    page.evaluate("window.dejaview.seek(0)")
    start = state(page)["positions"]["cube"]
    assert start == pytest.approx(s["result"]["initial_state"]["position"], abs=1e-4)
    page.evaluate("window.dejaview.seek(0.2)")
    end = state(page)
    assert end["animation"]["time"] == pytest.approx(0.2)
    assert end["positions"]["cube"] != start
    page.screenshot(path=artifacts / "4-scrubbed-end.png")

    # the exported scene: valid for the server's reader, with the moved source and new settings
    xml = page.evaluate("window.dejaview.exportXml()")
    (artifacts / "exported.xml").write_text(xml)
    scene = read_scene_string(xml, base_dir=web_root / "scenes", filename="exported.xml")
    cube = next(o for o in scene.objects if o.id == "cube")
    assert cube.pose.position[0] == pytest.approx(moved[0], abs=1e-6)
    assert scene.inference.iterations == 3 and scene.inference.heatmap.cells[0] == 2


def test_setup_edits_export_valid_xml(page, web_server, web_root):
    """Source, target, fixed/movable and rotation edits all land in XML the reader accepts."""
    open_viewer(page, web_server)
    load_scene(page, SCENE)
    page.evaluate("window.dejaview.setSource('ball')")
    page.evaluate("window.dejaview.setPose('#target', [0.6, 0.2, 0.05], [0.7071068, 0, 0, 0.7071068])")
    page.evaluate("window.dejaview.setPose('cube', [0.1, -0.1, 0.5], [0.9238795, 0.3826834, 0, 0])")
    page.evaluate("window.dejaview.setFixed('cube', true)")
    page.uncheck("#heatmap")
    page.dispatch_event("#heatmap", "change")
    xml = page.evaluate("window.dejaview.exportXml()")
    scene = read_scene_string(xml, base_dir=web_root / "scenes", filename="exported.xml")
    assert scene.inference.source == "ball" and scene.inference.heatmap is None
    assert scene.inference.target.position == pytest.approx((0.6, 0.2, 0.05))
    cube = next(o for o in scene.objects if o.id == "cube")
    assert cube.fixed and cube.pose.position == pytest.approx((0.1, -0.1, 0.5))
    assert cube.pose.orientation == pytest.approx((0.9238795, 0.3826834, 0, 0), abs=1e-6)
    assert "<!--" in xml  # what the viewer does not edit is kept as written


def test_a_bad_scene_is_reported_not_fatal(page, web_server):
    open_viewer(page, web_server)
    load_scene(page, SCENE)
    page.evaluate("window.dejaview.setSettings({iterations: 1000000})")  # over the server's limit
    page.evaluate("window.dejaview.run('solve')")
    page.wait_for_function("window.dejaview.state().notifications.some(n => n.kind === 'error')")
    errors = [n["text"] for n in state(page)["notifications"] if n["kind"] == "error"]
    assert any("limit_exceeded" in e for e in errors), errors
    assert state(page)["connected"]


def test_upload_a_scene_with_its_mesh_and_packing(page, web_server, web_root):
    """The file input takes the XML with its files; names resolve by file name; packings toggle."""
    open_viewer(page, web_server)
    page.set_input_files("#upload", [str(web_root / "scenes" / "toss.xml"),
                                     str(web_root / "meshes" / "cube.obj"),
                                     str(web_root / "packings" / "cube.spheres")])
    # the packing arrives after its object's mesh (a second fetch): wait for the scene's
    # "loaded" notice, sent once every object is complete, not for the meshes alone
    page.wait_for_function("(s => s.origin === '' && s.meshesLoaded === 4 && "
                           "s.notifications.some(n => n.text === 'loaded web-toss'))(window.dejaview.state())")
    s = state(page)
    assert s["scene"] == "web-toss" and s["packings"] == {"cube": {"spheres": 8, "visible": False}}
    page.check("#show-spheres")
    assert state(page)["packings"]["cube"]["visible"]
    assert not [n for n in s["notifications"] if n["kind"] == "error"]


def test_robot_links_are_drawn(page, web_server, artifacts):
    """A URDF robot: the server poses its links (forward kinematics), the viewer draws each of them,
    the mesh hand included; the screen shows them (pixels change where the forearm is when the
    robot is hidden)."""
    import io

    from PIL import Image

    open_viewer(page, web_server)
    loaded = load_scene(page, "scenes/arm.xml")
    assert loaded["robotLinks"] == {"arm": ["arm/base", "arm/turret", "arm/upper_arm", "arm/forearm",
                                            "arm/hand"]}
    # the forearm's centre in the world (yaw 0.5, pitch 0.35, elbow -0.35: level, 0.15 m past the elbow)
    reach = 0.4 * math.cos(0.35) + 0.15
    centre = [reach * math.cos(0.5), reach * math.sin(0.5), 0.4 - 0.4 * math.sin(0.35)]
    at = page.evaluate(f"window.dejaview.screenPoint('arm', {centre})")
    shown = Image.open(io.BytesIO(page.screenshot(path=artifacts / "robot-arm.png"))).convert("RGB")
    page.evaluate("window.dejaview.three.world.children.forEach(g => { "
                  "if (g.userData.objectId === 'arm') g.visible = false; })")
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    hidden = Image.open(io.BytesIO(page.screenshot())).convert("RGB")
    x, y = round(at["x"]), round(at["y"])
    a, b = shown.getpixel((x, y)), hidden.getpixel((x, y))
    assert sum(abs(p - q) for p, q in zip(a, b)) > 30, (a, b)


def test_a_moving_robot_is_played_with_the_trajectory(page, web_server):
    """A robot with joint keyframes: the set-up view shows it where it stands at time 0, a trajectory's
    playback moves its links (scrubbing to 0.1 s turns the arm by half of its 1 rad). (A job run from
    the viewer sends the scene's text, and a robot file named relative to it is refused there: the
    playback is fed a trajectory.csv.)"""
    open_viewer(page, web_server)
    load_scene(page, "scenes/arm_moving.xml")
    reach = 0.4 * math.cos(0.35) + 0.15
    height = 0.4 - 0.4 * math.sin(0.35)
    assert state(page)["linkPositions"]["arm/forearm"] == pytest.approx([reach, 0, height], abs=1e-4)
    # a trajectory of the ball (as a simulation's trajectory.csv) to play the scene along
    rows = "\n".join(f"{k},{0.01 * k:.2f},ball,-0.3,0.3,{0.6 - 0.5 * 9.81 * (0.01 * k) ** 2:.6f},1,0,0,0"
                     for k in range(31))
    page.evaluate("csv => window.dejaview.showTrajectoryCsv(csv)", "step,time,object,x,y,z,qw,qx,qy,qz\n" + rows)
    page.click("#play") if state(page)["animation"]["playing"] else None
    page.evaluate("window.dejaview.seek(0.1)")
    at = state(page)["linkPositions"]["arm/forearm"]
    assert at == pytest.approx([reach * math.cos(0.5), reach * math.sin(0.5), height], abs=1e-4)
    page.evaluate("window.dejaview.seek(0.3)")  # held after the last keyframe
    end = state(page)["linkPositions"]["arm/forearm"]
    assert end == pytest.approx([reach * math.cos(1.0), reach * math.sin(1.0), height], abs=1e-4)
    page.evaluate("window.dejaview.showSetup()")
    assert state(page)["linkPositions"]["arm/forearm"] == pytest.approx([reach, 0, height], abs=1e-4)
