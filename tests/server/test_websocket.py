"""The WebSocket endpoint under TestClient: every message type, every error, bare-text mode."""

from __future__ import annotations

import json

import pytest

from dejaview.sim.trajectory_csv import HEADER, read_trajectory_csv
from dejaview.server.messages import SERVER_MESSAGE

from .conftest import FIXTURES, receive, types, until_done

BALL_XML = (FIXTURES / "ball.xml").read_text()


def submit(ws, **fields):
    ws.send_text(json.dumps({"type": "submit", **fields}))


def check_typed(messages):
    for msg in messages:
        if isinstance(msg, dict):
            SERVER_MESSAGE.validate_python(msg)  # every message is a valid ServerMessage


def test_solve_streams_accepted_progress_trajectory_result_done(client):
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="solve", scene_path="ball.xml", request_id="r1")
        messages = until_done(ws)
    check_typed(messages)
    kinds = types(messages)
    assert kinds[0] == "accepted" and kinds[-3:] == ["trajectory", "result", "done"]
    assert set(kinds[1:-3]) == {"progress"}
    assert all(m["request_id"] == "r1" for m in messages)
    job_id = messages[0]["job_id"]
    assert all(m["job_id"] == job_id for m in messages)
    progress = [m for m in messages if m["type"] == "progress"]
    assert progress[-1]["iteration"] == progress[-1]["total"] == 3
    assert all(set(p) >= {"iteration", "loss", "best_loss", "elapsed_s"} for p in progress)
    traj, result, done = messages[-3:]
    assert traj["csv"].splitlines()[0] == ",".join(HEADER) and traj["bytes"] == len(traj["csv"])
    assert traj["url"] == f"http://testserver/jobs/{job_id}/trajectory.csv"
    assert client.get(traj["url"]).text == traj["csv"]
    assert result["result"]["source"] == "ball" and result["url"].endswith("/result.json")
    assert done["state"] == "done"


def test_simulate_from_xml_matches_the_library(client):
    from dejaview.scene import Scene
    from dejaview.sim.simulate import simulate

    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="simulate", scene_xml=BALL_XML, overrides={"steps": 7, "record_every": 2})
        messages = until_done(ws)
    (traj,) = [m for m in messages if m["type"] == "trajectory"]
    direct = simulate(Scene.from_xml(FIXTURES / "ball.xml"), steps=7, record_every=2).csv()
    assert traj["csv"] == direct
    assert read_trajectory_csv(traj["csv"])["ball"]["step"] == [0, 2, 4, 6, 7]


def test_payloads_over_the_inline_limit_come_as_urls_only(make_client):
    client = make_client(inline_limit_bytes=200)
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="solve", scene_path="ball.xml")
        messages = until_done(ws)
    traj = next(m for m in messages if m["type"] == "trajectory")
    result = next(m for m in messages if m["type"] == "result")
    assert "csv" not in traj and traj["bytes"] > 200 and "result" not in result
    assert read_trajectory_csv(client.get(traj["url"]).text)["ball"]["step"][-1] == 20
    assert client.get(result["url"]).json()["source"] == "ball"


def test_heatmap_messages(client):
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="heatmap", scene_path="ball.xml", overrides={"iterations": 1})
        messages = until_done(ws, timeout=120)
    check_typed(messages)
    assert messages[-1]["state"] == "done", messages[-2:]
    heat = next(m for m in messages if m["type"] == "heatmap")
    assert heat["ppm"].startswith("P3") and heat["png_url"].endswith("/heatmap.png")
    assert heat["grid"]["cells"] == [2, 2]
    assert types(messages)[-4:] == ["trajectory", "heatmap", "result", "done"]


def test_ping_pong_and_cancel(make_client):
    client = make_client(workers=1)
    with client.websocket_connect("/ws") as ws:
        ws.send_text(json.dumps({"type": "ping", "request_id": "p1"}))
        assert receive(ws) == {"type": "pong", "request_id": "p1"}
        submit(ws, kind="solve", scene_path="solve_endless.xml", request_id="long")
        accepted = receive(ws)
        job_id = accepted["job_id"]
        while (msg := receive(ws))["type"] != "progress":
            pass
        ws.send_text(json.dumps({"type": "cancel", "job_id": job_id}))
        rest = until_done(ws, job_id)
        assert rest[-1] == {"type": "done", "job_id": job_id, "request_id": "long", "state": "cancelled"}
        assert len([m for m in rest if m["type"] == "progress"]) <= 2
        # cancelling again: an error, and the connection goes on
        ws.send_text(json.dumps({"type": "cancel", "job_id": job_id, "request_id": "again"}))
        err = receive(ws)
        assert err["code"] == "not_cancellable" and err["request_id"] == "again" and err["job_id"] == job_id
        ws.send_text(json.dumps({"type": "cancel", "job_id": "f" * 32}))
        assert receive(ws)["code"] == "not_found"
        ws.send_text(json.dumps({"type": "ping"}))
        assert receive(ws) == {"type": "pong"}


def test_subscribe_to_running_and_finished_jobs(make_client):
    client = make_client(workers=1)
    with client.websocket_connect("/ws") as a, client.websocket_connect("/ws") as b:
        submit(a, kind="solve", scene_path="ball.xml", request_id="mine")
        job_id = receive(a)["job_id"]
        b.send_text(json.dumps({"type": "subscribe", "job_id": job_id, "request_id": "watch"}))
        seen_a, seen_b = until_done(a), until_done(b)
        assert types(seen_b)[-3:] == ["trajectory", "result", "done"]
        assert {m["request_id"] for m in seen_b} == {"watch"}
        assert seen_a[-3]["csv"] == seen_b[-3]["csv"]
        # a finished job replays its final messages
        b.send_text(json.dumps({"type": "subscribe", "job_id": job_id}))
        replay = until_done(b)
        assert types(replay) == ["trajectory", "result", "done"] and replay[0]["csv"] == seen_a[-3]["csv"]
        b.send_text(json.dumps({"type": "subscribe", "job_id": "e" * 32, "request_id": "x"}))
        assert receive(b) == {"type": "error", "code": "not_found", "message": f"no job '{'e' * 32}'",
                              "job_id": "e" * 32, "request_id": "x"}


def test_a_failed_job_sends_error_then_done(client, scene_root):
    # a scene the reader accepts but the simulator cannot build (at run time): a signed distance
    # grid of the 10 cm cube at 0.1 mm spacing would have 2.7e10 nodes
    bad = (BALL_XML.replace('restitution="0.2"/>', 'restitution="0.2" sdf-spacing="0.0001"/>')
           .replace("  <inference", '  <object id="block" mesh="meshes/cube.obj" fixed="true">'
                                    '<pose position="1 0 0.05"/></object>\n  <inference'))
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="simulate", scene_xml=bad, request_id="b")
        messages = until_done(ws)
    assert types(messages) == ["accepted", "error", "done"]
    assert messages[1]["code"] == "invalid_scene" and "spacing" in messages[1]["message"]
    assert messages[2]["state"] == "failed"


def test_a_start_area_that_cannot_hold_the_source_sends_its_error_then_done(client):
    """Issue 56: the job fails with ``infeasible_start_area`` and the one line; the connection
    goes on."""
    xml = (FIXTURES.parent / "inference" / "box_in_desk.xml").read_text()
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="solve", scene_xml=xml, request_id="desk")
        messages = until_done(ws)
        check_typed(messages)
        assert types(messages) == ["accepted", "error", "done"]
        assert messages[1]["code"] == "infeasible_start_area" and messages[1]["request_id"] == "desk"
        assert "cannot hold 'src': everywhere in it 'src' and 'desk' interpenetrate, by 0.0267 m" \
            in messages[1]["message"]
        assert messages[2]["state"] == "failed"
        ws.send_text(json.dumps({"type": "ping", "request_id": "p"}))
        assert receive(ws) == {"type": "pong", "request_id": "p"}


def test_a_backend_attribute_the_simulator_refuses_is_refused_at_submission(client):
    bad = BALL_XML.replace('restitution="0.2"/>', 'restitution="0.2" substeps="0"/>')
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="simulate", scene_xml=bad, request_id="b")
        message = receive(ws)
    assert message["type"] == "error" and message["code"] == "invalid_scene"
    assert "substeps='0' must be at least 1" in message["message"]


BAD_FRAMES = [
    ("{not json", "invalid_json"),
    ('{"type": "ping", "x": NaN}', "invalid_json"),
    ("[1, 2, 3]", "invalid_message"),
    ("42", "invalid_message"),
    ('"a string"', "invalid_message"),
    ("null", "invalid_message"),
    ('{"no_type": 1}', "invalid_message"),
    ('{"type": "explode"}', "unknown_type"),
    ('{"type": "submit", "kind": "solve"}', "invalid_message"),
    ('{"type": "submit", "kind": "solve", "scene_path": 5}', "invalid_message"),
    ('{"type": "submit", "kind": "solve", "scene_path": "ball.xml", "overrides": {"iterations": -5}}',
     "invalid_message"),
    ('{"type": "submit", "kind": "solve", "scene_path": "ball.xml", "overrides": {"lr": 1e999}}',
     "invalid_message"),
    ('{"type": "submit", "kind": "solve", "scene_path": "ball.xml", "overrides": {"optimizer": "newton"}}',
     "invalid_message"),
    ('{"type": "submit", "kind": "solve", "scene_path": "../outside/secret.xml"}', "path_outside_root"),
    ('{"type": "submit", "kind": "solve", "scene_path": "escape.xml"}', "path_outside_root"),
    ('{"type": "submit", "kind": "solve", "scene_xml": "<!DOCTYPE x [<!ENTITY a \\"b\\">]><scene/>"}',
     "invalid_scene"),
    ('{"type": "cancel", "job_id": "../../x"}', "invalid_message"),
    ("[" * 100_000 + "]" * 100_000, "invalid_json"),
]


@pytest.mark.parametrize("frame, code", BAD_FRAMES, ids=[c + str(i) for i, (_, c) in enumerate(BAD_FRAMES)])
def test_bad_frames_get_an_error_and_the_connection_stays(client, frame, code):
    with client.websocket_connect("/ws") as ws:
        ws.send_text(frame)
        err = receive(ws)
        assert err["type"] == "error" and err["code"] == code, err
        assert err["message"] and "\n" not in err["message"]
        ws.send_text('{"type": "ping"}')
        assert receive(ws) == {"type": "pong"}


def test_request_id_is_echoed_on_errors(client):
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="solve", scene_path="nope.xml", request_id="q7")
        err = receive(ws)
        assert err == {"type": "error", "code": "scene_not_found",
                       "message": "scene_path 'nope.xml': no such file in the scene root", "request_id": "q7"}


def test_binary_and_oversize_frames(make_client):
    client = make_client(max_message_bytes=10_000)
    with client.websocket_connect("/ws") as ws:
        ws.send_bytes(b"\x00\x01binary")
        assert receive(ws)["code"] == "binary_frame"
        ws.send_text(json.dumps({"type": "submit", "kind": "simulate", "scene_xml": " " * 20_000}))
        err = receive(ws)
        assert err["code"] == "message_too_large" and "10000" in err["message"]
        ws.send_text('{"type": "ping"}')
        assert receive(ws) == {"type": "pong"}


def test_message_rate_limit(make_client):
    client = make_client(messages_per_second=5)
    with client.websocket_connect("/ws") as ws:
        for i in range(40):
            ws.send_text(json.dumps({"type": "ping", "request_id": str(i)}))
        replies = [receive(ws) for _ in range(11)]  # 10 pongs (the burst) and one rate_limited
        assert [r["type"] for r in replies].count("pong") == 10
        limited = [r for r in replies if r["type"] == "error"]
        assert len(limited) == 1 and limited[0]["code"] == "rate_limited"
        assert "5 messages per second" in limited[0]["message"]


def test_too_many_jobs_per_connection(make_client):
    client = make_client(workers=1, max_jobs_per_connection=1)
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="solve", scene_path="solve_endless.xml")
        job_id = receive(ws)["job_id"]
        submit(ws, kind="simulate", scene_path="ball.xml", request_id="second")
        while (msg := receive(ws))["type"] == "progress":
            pass
        assert msg["code"] == "too_many_jobs" and msg["request_id"] == "second"
        ws.send_text(json.dumps({"type": "cancel", "job_id": job_id}))
        until_done(ws, job_id)
        submit(ws, kind="simulate", scene_path="drop.xml")
        assert until_done(ws)[-1]["state"] == "done"


def test_queue_full_over_websocket(make_client):
    client = make_client(workers=1, queue_size=1)
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="solve", scene_path="solve_endless.xml", request_id="a")
        submit(ws, kind="simulate", scene_path="drop.xml", request_id="b")
        submit(ws, kind="simulate", scene_path="drop.xml", request_id="c")
        got = {}
        while "c" not in got:
            msg = receive(ws)
            if msg["type"] in ("accepted", "error"):
                got[msg["request_id"]] = msg
        assert got["a"]["type"] == got["b"]["type"] == "accepted"
        assert got["b"]["queue_position"] == 1
        assert got["c"]["code"] == "queue_full"
        ws.send_text(json.dumps({"type": "cancel", "job_id": got["a"]["job_id"]}))


def test_disconnect_leaves_the_job_running(client):
    with client.websocket_connect("/ws") as ws:
        submit(ws, kind="solve", scene_path="ball.xml")
        job_id = receive(ws)["job_id"]
    from .test_rest import wait_state

    status = wait_state(client, job_id)
    assert status["state"] == "done" and "trajectory.csv" in status["artefacts"]


# ---------------------------------------------------------------- bare-text mode
def test_bare_text_path_gets_the_trajectory_csv(client):
    from dejaview.scene import Scene
    from dejaview.sim.simulate import simulate

    with client.websocket_connect("/ws") as ws:
        ws.send_text("drop.xml\n")
        csv_text = receive(ws)
    assert csv_text == simulate(Scene.from_xml(FIXTURES / "drop.xml")).csv()


def test_bare_text_scene_with_inference_is_solved(client):
    with client.websocket_connect("/ws") as ws:
        ws.send_text("throw.xml")
        text = receive(ws, timeout=120)
    traj = read_trajectory_csv(text)
    assert text.startswith(",".join(HEADER)) and traj["ball"]["step"][-1] == 20
    # the best solution, not the scene's guess (which starts at x = 0)
    assert traj["ball"]["position"][0] != [0.0, 0.0, 0.4]


def test_bare_text_heatmap_scene_gets_csv_then_ppm(client):
    with client.websocket_connect("/ws") as ws:
        ws.send_text("ball.xml")
        csv_text = receive(ws, timeout=120)
        assert csv_text.startswith(",".join(HEADER)), csv_text[:300]
        ppm = receive(ws, timeout=60)
    assert ppm.startswith("P3")


@pytest.mark.parametrize("frame, fragment", [
    ("missing.xml", "no such file"),
    ("../outside/secret.xml", "outside the scene root"),
    ("/etc/passwd", "absolute"),
    ("escape.xml", "outside the scene root"),
    ("", "must name a file"),
    ("\x01garbage\x7f", "no such file"),
    ("nul\x00byte.xml", "must name a file"),
])
def test_bare_text_errors_are_error_lines(client, frame, fragment):
    with client.websocket_connect("/ws") as ws:
        ws.send_text(frame)
        line = receive(ws)
        assert isinstance(line, str) and line.startswith("error: ") and fragment in line, line
        assert "\n" not in line
        ws.send_text('{"type": "ping"}')
        assert receive(ws) == {"type": "pong"}


def test_a_request_id_with_a_lone_surrogate_gets_an_error_not_a_crash(client):
    """JSON may escape a lone surrogate (\\udaf0), which no UTF-8 frame can carry back: the error
    leaves the request id out and the connection goes on (found by the 10^4-message fuzz)."""
    with client.websocket_connect("/ws") as ws:
        ws.send_text('{"type": "ping", "request_id": "a\\udaf0b"}')
        err = receive(ws)
        assert err["type"] == "error" and err["code"] == "invalid_message" and err.get("request_id") is None
        ws.send_text(json.dumps({"type": "ping", "request_id": "ok"}))
        assert receive(ws) == {"type": "pong", "request_id": "ok"}
