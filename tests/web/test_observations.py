"""Every observation of the source is drawn ("how the source was seen", issue 56): the tracked
example (``examples/scenes/box_tossed_tracked.xml``: position only at 0.15 s and 0.35 s, a pose at
0.6 s, a pose seen lying still at 1.2 s) shows four observations with their times; the scene's
XML keeps all four through the viewer's edits; playback lights each up as it passes its time; the
result panel gives the end's distance from where the source was seen lying, each observation's, the
rest time and the warnings. Scenes load from a real ``dejaview serve``; the results of the playback
and warning tests come from a stand-in for the WebSocket (Playwright's ``route_web_socket``)."""

from __future__ import annotations

import json
import re

import pytest

from dejaview.scene import Scene
from dejaview.scene.xml import read_scene_string

from .conftest import REPO, load_scene, needs_browser, open_viewer, state

pytestmark = needs_browser
TRACKED = "examples/scenes/box_tossed_tracked.xml"
EXAMPLE = Scene.from_xml(REPO / TRACKED)


def observations(page) -> list[dict]:
    return state(page)["observations"]


def test_the_tracked_example_draws_each_observation(page, web_server, artifacts):
    open_viewer(page, web_server)
    loaded = load_scene(page, TRACKED)
    obs = loaded["observations"]
    assert [o["kind"] for o in obs] == ["position", "position", "pose", "pose"]
    assert [o["label"] for o in obs] == ["0.15 s", "0.35 s", "0.60 s", "1.20 s, at rest"]
    assert [o["last"] for o in obs] == [False, False, False, True] and all(o["shown"] for o in obs)
    for o, target in zip(obs, EXAMPLE.inference.targets):
        assert o["position"] == pytest.approx(list(target.position), abs=1e-6)
    assert [t["time"] for t in loaded["targets"]] == [0.15, 0.35, 0.6, 1.2]
    assert [t["atRest"] for t in loaded["targets"]] == [False, False, False, True]
    # in the three.js scene: a group and a label per observation, and the dashed line through them
    names = page.evaluate("window.dejaview.three.world.children.map(c => c.name)")
    assert sum(n.startswith("observation-label-") for n in names) == 4
    assert sum(re.fullmatch(r"observation-\d", n) is not None for n in names) == 4
    assert "observation-line" in names
    page.screenshot(path=artifacts / "tracked-observations.png")

    # the "Target" button selects the last observation (the pose seen lying still at 1.2 s)
    page.click("#select-target")
    s = state(page)
    assert s["selected"] == "#target" and s["gizmoAttached"]
    assert "target (1.20 s, at rest)" in page.inner_text("#selection")
    # an earlier observation is picked with the mouse like any object
    at = page.evaluate("window.dejaview.screenPoint('#target:1')")
    page.mouse.click(at["x"], at["y"])
    assert state(page)["selected"] == "#target:1"
    assert "observation (0.35 s, position only)" in page.inner_text("#selection")


def test_xml_round_trip_keeps_every_observation(page, web_server, web_root):
    open_viewer(page, web_server)
    load_scene(page, TRACKED)
    base = web_root / "examples" / "scenes"

    untouched = read_scene_string(page.evaluate("window.dejaview.exportXml()"), base_dir=base, filename="x.xml")
    assert untouched.inference.targets == EXAMPLE.inference.targets

    # the Target edits the last observation (its orientation too); an earlier position-only one
    # moves and stays position-only; time and moving edit through the model
    page.evaluate("window.dejaview.setPose('#target', [0.8, 0.3, 0.05], [0.7071068, 0, 0, 0.7071068])")
    page.evaluate("window.dejaview.setPose('#target:0', [0.25, -0.05, 0.6], [0.7071068, 0.7071068, 0, 0])")
    page.evaluate("window.dejaview.setObservation(1, {time: 0.4})")
    page.evaluate("window.dejaview.setObservation(2, {moving: true})")
    edited = read_scene_string(page.evaluate("window.dejaview.exportXml()"), base_dir=base, filename="x.xml")
    t = edited.inference.targets
    assert len(t) == 4
    assert t[0].position == pytest.approx((0.25, -0.05, 0.6)) and t[0].orientation is None and t[0].time == 0.15
    assert t[1].time == 0.4 and t[1].orientation is None and t[1].position == EXAMPLE.inference.targets[1].position
    assert t[2].moving is True and t[2].orientation == EXAMPLE.inference.targets[2].orientation
    assert t[3].position == pytest.approx((0.8, 0.3, 0.05)) and t[3].time == 1.2 and t[3].moving is False
    assert t[3].orientation == pytest.approx((0.7071068, 0, 0, 0.7071068), abs=1e-6)
    assert edited.inference.target == t[3]
    assert [o["label"] for o in observations(page)] == ["0.15 s", "0.40 s", "0.60 s", "1.20 s, at rest"]

    # observations added and removed: what is drawn follows
    page.evaluate("window.dejaview.addObservation({position: [0.78, 0.25, 0.07], time: 0.9})")
    assert [o["label"] for o in observations(page)][-1] == "0.90 s"
    page.evaluate("window.dejaview.removeObservation(0)")
    xml = page.evaluate("window.dejaview.exportXml()")
    times = [x.time for x in read_scene_string(xml, base_dir=base, filename="x.xml").inference.targets]
    assert times == [0.4, 0.6, 1.2, 0.9] and len(observations(page)) == 4
    assert "<!--" in xml  # what the viewer does not edit is kept as written


RESULT = {
    "source": "box", "loss": 0.0021,
    "end_error": {"time": 1.2, "position_error": 0.0002, "angle_error_deg": 0.6},
    "observations": [
        {"target_time": 0.15, "at_rest": False, "time": 0.15, "position_error": 0.0031, "angle_error_deg": None,
         "position": [0.26, -0.04, 0.63], "orientation": [1, 0, 0, 0]},
        {"target_time": 0.35, "at_rest": False, "time": 0.35, "position_error": 0.012, "angle_error_deg": None,
         "position": [0.54, 0.03, 0.37], "orientation": [1, 0, 0, 0]},
        {"target_time": 0.6, "at_rest": False, "time": 0.6, "position_error": 0.002, "angle_error_deg": 1.25,
         "position": [0.74, 0.2, 0.09], "orientation": [1, 0, 0, 0]},
        {"target_time": 1.2, "at_rest": True, "time": 1.2, "position_error": 0.0002, "angle_error_deg": 0.6,
         "position": [0.8, 0.27, 0.07], "orientation": [1, 0, 0, 0]},
    ],
    "targets": [{"position": [0, 0, 0], "orientation": None, "time": 0.15, "at_rest": False},
                {"position": [0, 0, 0], "orientation": None, "time": 0.35, "at_rest": False},
                {"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "time": 0.6, "at_rest": False},
                {"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "time": 1.2, "moving": False,
                 "at_rest": True}],
    "rest": {"came_to_rest_s": None, "needs_duration_s": 1.6},
    "warnings": ["the answer is still moving at the end of the simulation (1.2 s); it comes to rest by "
                 "1.52 s: set <simulation duration=\"1.6\"> or longer"],
}


def trajectory_csv(duration: float = 1.2, dt: float = 0.01) -> str:
    """The box flying from (0, 0, 0.5) to (0.8, 0.27, 0.07), and the floor still."""
    rows = ["step,time,object,x,y,z,qw,qx,qy,qz"]
    steps = round(duration / dt)
    for k in range(steps + 1):
        u = k / steps
        rows.append(f"{k},{k * dt:.6f},box,{0.8 * u:.6f},{0.27 * u:.6f},{0.5 - 0.43 * u:.6f},1,0,0,0")
        rows.append(f"{k},{k * dt:.6f},floor,0,0,0,1,0,0,0")
    return "\n".join(rows) + "\n"


def fake_server(result: dict, csv: str | None = None):
    """A WebSocket handler answering a submit with accepted, the trajectory (when given), the
    result and done."""

    def handler(ws):
        def on_message(text):
            msg = json.loads(text)
            if msg.get("type") != "submit":
                return
            job = {"job_id": "job0", "request_id": msg.get("request_id")}
            ws.send(json.dumps({**job, "type": "accepted", "kind": msg["kind"], "state": "queued"}))
            if csv is not None:
                ws.send(json.dumps({**job, "type": "trajectory", "csv": csv, "url": "jobs/job0/trajectory.csv",
                                    "bytes": len(csv)}))
            ws.send(json.dumps({**job, "type": "result", "result": result, "url": "jobs/job0/result.json"}))
            ws.send(json.dumps({**job, "type": "done", "state": "done"}))

        ws.on_message(on_message)

    return handler


def solve(page) -> dict:
    page.click("#run-solve")
    page.wait_for_function("window.dejaview.state().jobs.some(j => j.state === 'done')")
    return state(page)


def test_a_result_shows_the_end_each_observation_and_its_warnings(page, web_server, artifacts):
    page.route_web_socket(re.compile(r".*/ws(\?.*)?$"), fake_server(RESULT))
    open_viewer(page, web_server)
    load_scene(page, TRACKED)
    s = solve(page)
    warnings = [n["text"] for n in s["notifications"] if n["kind"] == "warning"]
    assert warnings == RESULT["warnings"]
    assert page.locator("#notifications li.warning").count() == 1  # the R-hat warning's look
    summary = s["resultSummary"]
    assert {"kind": "end", "text": "ends 0.2 mm / 0.6° from where it was seen lying"} in summary
    assert {"kind": "info", "text": "still moving at the end (it needs about 1.60 s)"} in summary
    assert [line["text"] for line in summary if line["kind"] == "observation"] == [
        "0.15 s (position only): 3.1 mm", "0.35 s (position only): 12 mm", "0.60 s: 2.0 mm / 1.3°",
        "1.20 s (at rest): 0.2 mm / 0.6°"]
    assert [line["text"] for line in summary if line["kind"] == "warning"] == RESULT["warnings"]
    assert page.locator("#result-summary li.warning").count() == 1
    page.screenshot(path=artifacts / "tracked-result-warnings.png")


def test_playback_lights_each_observation_up_as_it_passes(page, web_server, artifacts):
    page.route_web_socket(re.compile(r".*/ws(\?.*)?$"), fake_server(RESULT, trajectory_csv()))
    open_viewer(page, web_server)
    load_scene(page, TRACKED)
    solve(page)
    page.wait_for_function("window.dejaview.state().trajectoryShown")
    page.click("#play")  # pause: the tests scrub
    lit = lambda: [o["highlighted"] for o in observations(page)]  # noqa: E731
    page.evaluate("window.dejaview.seek(0.05)")
    assert lit() == [False, False, False, False]
    page.evaluate("window.dejaview.seek(0.16)")
    assert lit() == [True, False, False, False]
    page.evaluate("window.dejaview.seek(0.35)")
    assert lit() == [False, True, False, False]
    page.screenshot(path=artifacts / "tracked-playback-0.35s.png")
    page.evaluate("window.dejaview.seek(0.62)")
    assert lit() == [False, False, True, False]
    page.evaluate("window.dejaview.seek(1.2)")
    assert lit() == [False, False, False, True]
    page.click("#setup-view")
    assert lit() == [False, False, False, False]
    # played in real time, each observation lights up on the way
    page.evaluate("window.dejaview.seek(0); window.dejaview.play()")
    page.wait_for_function("window.dejaview.state().observations[1].highlighted")


def test_a_real_solve_of_the_tracked_scene_reports_each_observation(page, web_server):
    """The service's own result.json for the tracked example: the panel lists the end and all four
    observations."""
    open_viewer(page, web_server)
    load_scene(page, TRACKED)
    page.evaluate("window.dejaview.setSettings({iterations: 2})")
    page.click("#run-solve")
    page.wait_for_function("window.dejaview.state().jobs.some(j => j.state === 'done' || j.state === 'failed')",
                           timeout=240_000)
    s = state(page)
    assert [j["state"] for j in s["jobs"]] == ["done"], s["notifications"][-3:]
    summary = s["resultSummary"]
    end = [line["text"] for line in summary if line["kind"] == "end"]
    assert len(end) == 1 and end[0].startswith("ends ") and end[0].endswith("from where it was seen lying")
    rows = [line["text"] for line in summary if line["kind"] == "observation"]
    assert [r.split(":")[0] for r in rows] == ["0.15 s (position only)", "0.35 s (position only)", "0.60 s",
                                               "1.20 s (at rest)"]
    assert any(line["text"].startswith(("came to rest at", "still moving")) for line in summary)


def test_a_source_seen_moving_gets_its_best_match_beside_the_end(page, web_server):
    """One target without time, seen moving, position only (the web toss scene): the end's distance
    without an angle, and the moment the answer passes the observation (``matched``)."""
    result = {"source": "cube", "loss": 0.01, "warnings": [],
              "end_error": {"time": 0.2, "position_error": 0.0412, "angle_error_deg": None},
              "observations": [{"target_time": None, "at_rest": False, "time": 0.2, "position_error": 0.0412,
                                "angle_error_deg": None, "position": [0.1, 0, 0.2], "orientation": [1, 0, 0, 0],
                                "matched": {"time": 0.13, "position_error": 0.0009, "angle_error_deg": None,
                                            "position": [0.2, 0.05, 0.25], "orientation": [1, 0, 0, 0]}}],
              "targets": [{"position": [0.2, 0.05, 0.25], "orientation": None, "moving": True, "at_rest": False}],
              "rest": {"came_to_rest_s": None}}
    page.route_web_socket(re.compile(r".*/ws(\?.*)?$"), fake_server(result))
    open_viewer(page, web_server)
    loaded = load_scene(page, "scenes/toss.xml")
    assert [(o["kind"], o["label"], o["last"]) for o in loaded["observations"]] == [("position", "seen moving", True)]
    summary = [line["text"] for line in solve(page)["resultSummary"]]
    assert summary == ["best loss 0.0100", "ends 41 mm from where it was seen moving", "still moving at the end",
                       "end (seen moving, position only): 41 mm", "  passes it at 0.13 s: 0.9 mm"]
