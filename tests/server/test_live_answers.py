"""Live answers (protocol addition "Live answers"): a train job, then ``live`` messages answered from
its model in the server process; ``no_model``; coalescing; bad live messages. No timing asserts:
``bench/live.py`` measures the latency."""

from __future__ import annotations

import asyncio
import json
import math
import re

import pytest

pytest.importorskip("zuko", reason="the amortised extra (pip install 'dejaview[amortised]')")

from fastapi.testclient import TestClient  # noqa: E402

from dejaview.server.app import create_app  # noqa: E402
from dejaview.server.live import LiveQueue  # noqa: E402
from dejaview.server.messages import SERVER_MESSAGE  # noqa: E402

from .conftest import FIXTURES, make_scene_root, receive, until_done  # noqa: E402
from .test_rest import wait_state  # noqa: E402

THROW_XML = (FIXTURES / "throw.xml").read_text()
TARGET = [0.2, 0.05, 0.25]  # throw.xml's
TINY = {"simulations": 400, "epochs": 15, "patience": 5, "transforms": 2, "hidden": [32, 32], "batch": 128,
        "lr": 0.003}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A server (thread workers) whose models folder holds throw.xml's model, trained by a train job;
    yields (client, the train job's messages)."""
    base = tmp_path_factory.mktemp("live-answers")
    client = TestClient(create_app(scene_root=make_scene_root(base), results_dir=base / "results", workers=2,
                                   executor="thread", progress_interval_s=0.0))
    client.__enter__()
    with client.websocket_connect("/ws") as ws:
        ws.send_text(json.dumps({"type": "submit", "kind": "train", "scene_path": "throw.xml", "overrides": TINY,
                                 "request_id": "t"}))
        messages = until_done(ws, timeout=300)
    yield client, messages
    client.__exit__(None, None, None)


def live(ws, target=TARGET, request_id="r", **fields):
    fields.setdefault("scene_path", "throw.xml")
    ws.send_text(json.dumps({"type": "live", "target": {"position": target}, "request_id": request_id, **fields}))


def next_live(ws) -> dict:
    """The next live-result or error (progress of other jobs skipped)."""
    while True:
        msg = receive(ws, 120)
        if msg["type"] in ("live-result", "error"):
            SERVER_MESSAGE.validate_python(msg)
            return msg


def test_train_job_reports_progress_and_writes_its_model_beside_the_results(server):
    client, messages = server
    kinds = [m["type"] for m in messages]
    assert kinds[0] == "accepted" and kinds[-2:] == ["result", "done"] and messages[-1]["state"] == "done"
    phases = {m.get("phase") for m in messages if m["type"] == "progress"}
    assert phases == {"simulate", "fit"}
    result = messages[-2]["result"]
    assert result["kind"] == "train" and result["simulations"] == 400
    fingerprint = result["fingerprint"]
    path = client.app.state.config.results_dir / "models" / f"{fingerprint}.safetensors"
    assert result["model"] == f"models/{fingerprint}.safetensors" and path.is_file()
    status = client.get(f"/jobs/{messages[0]['job_id']}").json()
    assert status["kind"] == "train" and status["summary"]["fingerprint"] == fingerprint


def test_a_train_jobs_model_downloads_and_loads(server, tmp_path):
    """``GET /jobs/{id}/model``: the file in the models folder, byte for byte, which the project's
    loader reads; not for other kinds of job, an unknown job, or once a later train job replaced it."""
    from dejaview.inference.amortised import AmortisedModel

    client, messages = server
    job_id = messages[0]["job_id"]
    fingerprint = messages[-2]["result"]["fingerprint"]
    stored = client.app.state.config.results_dir / "models" / f"{fingerprint}.safetensors"
    response = client.get(f"/jobs/{job_id}/model")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/octet-stream"
    assert response.headers["content-disposition"] == f'attachment; filename="{fingerprint}.safetensors"'
    assert response.content == stored.read_bytes()
    (tmp_path / "got.safetensors").write_bytes(response.content)
    assert AmortisedModel.load(tmp_path / "got.safetensors").fingerprint == fingerprint

    solve = client.post("/jobs", json={"kind": "solve", "scene_path": "ball.xml", "overrides": {"iterations": 2}})
    solve_id = solve.json()["job_id"]
    assert wait_state(client, solve_id)["state"] == "done"
    response = client.get(f"/jobs/{solve_id}/model")
    assert response.status_code == 404 and response.json() == {
        "code": "no_artefact", "message": f"job {solve_id} is a solve job: only train jobs have a model"}
    assert client.get(f"/jobs/{'0' * 32}/model").json()["code"] == "not_found"

    original = stored.read_bytes()
    try:  # a later train job of the same scene wrote another model there
        stored.write_bytes(original[:-1] + bytes([original[-1] ^ 1]))
        response = client.get(f"/jobs/{job_id}/model")
        assert response.status_code == 404 and "replaced" in response.json()["message"]
    finally:
        stored.write_bytes(original)
    assert client.get(f"/jobs/{job_id}/model").status_code == 200


def test_live_answer_is_the_flow_at_the_moved_target(server):
    """The answer equals the library's ``live`` for the scene with its target moved there: the
    cached observation vector with the new target is the moved scene's own."""
    import torch

    from dejaview.inference.amortised import AmortisedModel
    from dejaview.inference.amortised.answer import live as library_live
    from dejaview.inference.params import AmortisedParams
    from dejaview.inference.posterior import Posterior
    from dejaview.scene import Scene

    client, messages = server
    moved = [0.25, -0.02, 0.2]
    with client.websocket_connect("/ws") as ws:
        live(ws, target=moved, request_id="m1", cells=[6, 5])
        got = next_live(ws)
    assert got["type"] == "live-result" and got["request_id"] == "m1", got
    config = client.app.state.config
    model = AmortisedModel.load(config.results_dir / "models" / f"{got['model']}.safetensors")
    scene = Scene.from_string(THROW_XML.replace('position="0.2 0.05 0.25"', 'position="0.25 -0.02 0.2"'))
    want = library_live(Posterior.from_scene(scene), model, params=AmortisedParams(live_draws=config.live_draws),
                        cells=(6, 5))
    assert len(got["samples"]) == config.live_samples < config.live_draws
    assert torch.allclose(torch.tensor(got["samples"], dtype=torch.float64),
                          want["samples"][:config.live_samples], atol=1e-5)
    assert got["heatmap"]["cells"] == [6, 5] and got["heatmap"]["probability"] == want["heatmap"]["probability"]
    assert math.isclose(sum(map(sum, got["heatmap"]["probability"])), 1.0)
    assert got["most_probable"] == want["most_probable"] and got["fitted"] == want["fitted"]
    assert got["draws"] == config.live_draws


def test_live_answers_lie_in_the_start_area_and_know_a_target_never_trained_for(server):
    client, _ = server
    with client.websocket_connect("/ws") as ws:
        live(ws, request_id="near")
        near = next_live(ws)
        live(ws, target=[5.0, 5.0, 3.0], request_id="far")
        far = next_live(ws)
    assert near["fitted"] and not far["fitted"]
    for answer in (near, far):
        assert answer["heatmap"]["min"] == [-0.1, -0.1] and answer["heatmap"]["max"] == [0.1, 0.1]
        assert all(-0.1 <= x <= 0.1 and -0.1 <= y <= 0.1 and z == pytest.approx(0.4) for x, y, z in answer["samples"])
    assert near["samples"] != far["samples"]


def test_a_scene_without_a_model_gets_no_model(server):
    """Another start area is another fingerprint: the model of throw.xml is not found for it."""
    client, _ = server
    other = THROW_XML.replace('min="-0.1 -0.1 0.4" max="0.1 0.1 0.4"', 'min="-0.1 -0.1 0.45" max="0.1 0.1 0.45"')
    assert other != THROW_XML
    with client.websocket_connect("/ws") as ws:
        ws.send_text(json.dumps({"type": "live", "scene_xml": other, "target": {"position": TARGET},
                                 "request_id": "x"}))
        err = next_live(ws)
        live(ws, request_id="still")  # the connection goes on
        ok = next_live(ws)
    assert err["type"] == "error" and err["code"] == "no_model" and err["request_id"] == "x"
    assert "train" in err["message"] and "\n" not in err["message"]
    assert ok["type"] == "live-result" and ok["request_id"] == "still"


def test_a_burst_of_live_messages_is_answered_newest_last_and_never_more_than_sent(server):
    client, _ = server
    sent = [f"b{i}" for i in range(15)]
    with client.websocket_connect("/ws") as ws:
        for i, rid in enumerate(sent):
            live(ws, target=[0.1 + 0.01 * i, 0.0, 0.25], request_id=rid)
        answered = []
        while not answered or answered[-1] != sent[-1]:
            msg = next_live(ws)
            assert msg["type"] == "live-result", msg
            answered.append(msg["request_id"])
        ws.send_text(json.dumps({"type": "ping", "request_id": "after"}))
        assert receive(ws)["type"] == "pong"  # nothing else came after the newest's answer
    assert len(answered) <= len(sent) and len(set(answered)) == len(answered)
    assert [sent.index(r) for r in answered] == sorted(sent.index(r) for r in answered)


def test_live_queue_answers_one_at_a_time_then_only_the_newest():
    """While one answer is computed, later messages wait; of them only the newest is answered."""
    async def scenario():
        release = asyncio.Event()
        started, sent = [], []

        async def answer(message):
            started.append(message)
            if message == "m0":
                await release.wait()
            return f"answer to {message}"

        queue = LiveQueue(answer, sent.append, lambda exc, m: sent.append(f"error {m}"))
        queue.put("m0")
        await asyncio.sleep(0)
        for i in range(1, 6):
            queue.put(f"m{i}")
        assert started == ["m0"]
        release.set()
        await queue.task
        return started, sent, queue.dropped

    started, sent, dropped = asyncio.run(scenario())
    assert started == ["m0", "m5"] and sent == ["answer to m0", "answer to m5"] and dropped == 4


BAD = [
    ('{"type":"live","scene_path":"throw.xml","target":{"position":[0.1,NaN,0.2]},"request_id":"nan"}',
     "invalid_json"),
    ({"target": {"position": [0.1, 0.2]}}, "invalid_message"),
    ({"target": {"position": [0.1, 0.2, 0.3, 0.4]}}, "invalid_message"),
    ({"target": {"position": [0.1, "0.2", 0.3]}}, "invalid_message"),
    ({"target": {"position": [0.1, True, 0.3]}}, "invalid_message"),
    ({"target": {"position": [0.1, 1e300, 0.3]}}, "invalid_message"),
    ({"target": {"position": [0.1, 0.2, 0.3], "orientation": [0, 0, 0, 0]}}, "invalid_message"),
    ({"target": {"position": [0.1, 0.2, 0.3], "orientation": [1, 0, 0]}}, "invalid_message"),
    ({"target": {"position": [0.1, 0.2, 0.3], "velocity": [1, 0, 0]}}, "invalid_message"),
    ({"target": "here"}, "invalid_message"),
    ({"target": None}, "invalid_message"),  # none given
    ({"cells": [0, 4]}, "invalid_message"),
    ({"cells": [1000, 1000]}, "invalid_message"),
    ({"scene_xml": THROW_XML}, "invalid_message"),  # and a scene_path
    ({"scene_path": None, "scene_xml": '<?xml version="1.0"?><!DOCTYPE s [<!ENTITY a "aaaa"><!ENTITY b '
      '"&a;&a;&a;&a;">]><scene version="1">&b;</scene>'}, "invalid_scene"),
    ({"scene_path": None, "scene_xml": "<scene"}, "invalid_scene"),
    ({"scene_path": None, "scene_xml": re.sub(r"\s*<start-area[^>]*/>", "", THROW_XML)}, "invalid_scene"),
    ({"scene_path": "../outside/secret.xml"}, "path_outside_root"),
    ({"scene_path": "escape.xml"}, "path_outside_root"),
    ({"scene_path": "missing.xml"}, "scene_not_found"),
    ({"scene_path": "drop.xml"}, "invalid_scene"),  # no <inference>
]


def test_bad_live_messages_get_one_line_errors_and_the_server_goes_on(server):
    client, _ = server
    with client.websocket_connect("/ws") as ws:
        for i, (fields, code) in enumerate(BAD):
            if isinstance(fields, str):
                ws.send_text(fields)
            else:
                message = {"type": "live", "scene_path": "throw.xml", "target": {"position": TARGET},
                           "request_id": f"bad{i}", **fields}
                ws.send_text(json.dumps({k: v for k, v in message.items() if v is not None}))
            err = next_live(ws)
            assert err["type"] == "error" and err["code"] == code, (fields, err)
            assert "\n" not in err["message"] and err["message"]
            if not isinstance(fields, str):
                assert err["request_id"] == f"bad{i}"
        live(ws, request_id="good")
        good = next_live(ws)
    assert good["type"] == "live-result" and good["request_id"] == "good"
    assert client.get("/health").json()["status"] == "ok"


def test_train_jobs_are_checked_like_the_others(server):
    client, _ = server
    body = {"kind": "train", "scene_path": "throw.xml"}
    r = client.post("/jobs", json={**body, "overrides": {"iterations": 3}})
    assert r.status_code == 422 and "does not apply to train jobs" in r.json()["message"]
    r = client.post("/jobs", json={**body, "overrides": {"simulations": 10 ** 7}})
    assert r.status_code == 422 and r.json()["code"] == "limit_exceeded"
    r = client.post("/jobs", json={"kind": "train", "scene_path": "drop.xml"})
    assert r.status_code == 422 and r.json()["code"] == "invalid_scene"


def test_a_train_job_can_be_cancelled(server):
    client, _ = server
    with client.websocket_connect("/ws") as ws:
        ws.send_text(json.dumps({"type": "submit", "kind": "train", "scene_path": "throw.xml",
                                 "overrides": {"simulations": 150_000, "seed": 7}, "request_id": "c"}))
        job_id = receive(ws)["job_id"]
        while receive(ws, 120)["type"] != "progress":
            pass
        ws.send_text(json.dumps({"type": "cancel", "job_id": job_id}))
        messages = until_done(ws, job_id, timeout=120)
    assert messages[-1]["state"] == "cancelled"
    assert client.get(f"/jobs/{job_id}").json()["state"] == "cancelled"


def test_live_messages_have_their_own_rate_budget(server):
    """A flood of live messages is cut by the live budget (one rate_limited error) and leaves the
    connection's budget for other messages whole: a ping after it is answered."""
    client, _ = server
    with client.websocket_connect("/ws") as ws:
        for i in range(400):  # the live budget: bursts of 120, 60 more a second
            live(ws, request_id=f"f{i}")
        ws.send_text(json.dumps({"type": "ping", "request_id": "p"}))
        seen = []
        while True:
            msg = receive(ws, 120)
            seen.append(msg)
            if msg["type"] == "pong":
                break
    limited = [m for m in seen if m["type"] == "error" and m["code"] == "rate_limited"]
    assert limited and all("live messages per second" in m["message"] for m in limited)
    assert all(m["type"] in ("live-result", "error") for m in seen[:-1])
