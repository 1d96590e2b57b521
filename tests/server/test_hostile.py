"""Hostile input against a real server: every kind of bad input gets an error (message, line or
status), nothing closes other connections, and other clients' jobs finish with correct results."""

from __future__ import annotations

import asyncio
import json
import urllib.error
import urllib.request

import pytest

from dejaview.server.client import submit_job, wait_healthy

from .conftest import FIXTURES

BALL_XML = (FIXTURES / "ball.xml").read_text()
THROW_XML = (FIXTURES / "throw.xml").read_text()

BILLION_LAUGHS = """<?xml version="1.0"?>
<!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
<!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">
<!ENTITY lol9 "&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;">]>
<scene version="1" name="&lol9;"/>"""
EXTERNAL_ENTITY = """<?xml version="1.0"?>
<!DOCTYPE scene [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>
<scene version="1" name="&xxe;"/>"""
XINCLUDE = """<scene version="1" xmlns:xi="http://www.w3.org/2001/XInclude">
  <xi:include href="file:///etc/passwd" parse="text"/></scene>"""
NAN_XML = BALL_XML.replace('<pose position="0 0 0.4"/>', '<pose position="nan 0 0.4"/>')
MESH_OUT = BALL_XML.replace('shape="sphere" radius="0.05"', 'mesh="../outside/secret.obj"')


def submit(**fields) -> str:
    return json.dumps({"type": "submit", **fields})


# (name, frame, expected error code); a bare-text frame expects an "error:" line (code None)
WS_CASES = [
    ("garbage", "\x01\x02 garbage ~~~", None),
    ("broken JSON", '{"type": "submit", "kind": ', "invalid_json"),
    ("JSON array", "[1, 2, 3]", "invalid_message"),
    ("unknown type", '{"type": "format_disk"}', "unknown_type"),
    ("missing type", '{"kind": "solve"}', "invalid_message"),
    ("missing scene", submit(kind="solve"), "invalid_message"),
    ("missing kind", '{"type": "submit", "scene_path": "ball.xml"}', "invalid_message"),
    ("wrong type of field", submit(kind="solve", scene_path=["ball.xml"]), "invalid_message"),
    ("iterations as text", submit(kind="solve", scene_path="ball.xml", overrides={"iterations": "ten"}),
     "invalid_message"),
    ("NaN in overrides", '{"type": "submit", "kind": "solve", "scene_path": "ball.xml", '
                         '"overrides": {"lr": NaN}}', "invalid_json"),
    ("infinity in overrides", '{"type": "submit", "kind": "solve", "scene_path": "ball.xml", '
                              '"overrides": {"sigma": 1e999}}', "invalid_message"),
    ("negative iterations", submit(kind="solve", scene_path="ball.xml", overrides={"iterations": -3}),
     "invalid_message"),
    ("unknown optimizer", submit(kind="solve", scene_path="ball.xml", overrides={"optimizer": "magic"}),
     "invalid_message"),
    ("unknown override", submit(kind="solve", scene_path="ball.xml", overrides={"rm": "-rf"}),
     "invalid_message"),
    ("override of another kind", submit(kind="simulate", scene_path="ball.xml", overrides={"iterations": 3}),
     "invalid_message"),
    ("huge job", submit(kind="solve", scene_path="ball.xml", overrides={"iterations": 10 ** 9}),
     "limit_exceeded"),
    ("XML bomb", submit(kind="simulate", scene_xml=BILLION_LAUGHS), "invalid_scene"),
    ("external entity", submit(kind="simulate", scene_xml=EXTERNAL_ENTITY), "invalid_scene"),
    ("XInclude", submit(kind="simulate", scene_xml=XINCLUDE), "invalid_scene"),
    ("NaN in the XML", submit(kind="simulate", scene_xml=NAN_XML), "invalid_scene"),
    ("not XML", submit(kind="simulate", scene_xml="{}"), "invalid_scene"),
    ("path traversal", submit(kind="simulate", scene_path="../outside/secret.xml"), "path_outside_root"),
    ("absolute path", submit(kind="simulate", scene_path="/etc/passwd"), "path_outside_root"),
    ("symlink out of the root", submit(kind="simulate", scene_path="escape.xml"), "path_outside_root"),
    ("symlinked folder", submit(kind="simulate", scene_path="linked/secret.xml"), "path_outside_root"),
    ("mesh escaping the root", submit(kind="simulate", scene_xml=MESH_OUT), "path_outside_root"),
    ("bare path traversal", "../outside/secret.xml", None),
    ("cancel a forged id", '{"type": "cancel", "job_id": "../../../etc/passwd"}', "invalid_message"),
    ("cancel an unknown job", '{"type": "cancel", "job_id": "' + "a" * 32 + '"}', "not_found"),
    ("deep nesting", "[" * 200_000 + "]" * 200_000, "invalid_json"),
    ("huge request id", json.dumps({"type": "ping", "request_id": "x" * 10_000}), "invalid_message"),
    ("huge frame", submit(kind="simulate", scene_xml=" " * (3 << 20)), "message_too_large"),
]


async def hostile_session(url: str) -> list[tuple[str, object, str | None]]:
    """Send every bad frame on ONE connection; returns (name, reply, expected code)."""
    from websockets.asyncio.client import connect

    replies = []
    async with connect(url, max_size=None) as ws:
        for name, frame, code in WS_CASES:
            await ws.send(frame)
            reply = await asyncio.wait_for(ws.recv(), 60)
            replies.append((name, reply, code))
            await asyncio.sleep(0.03)  # stay under the rate limit: the flood has its own test
        await ws.send(b"\x00\xffbinary")
        replies.append(("binary frame", await asyncio.wait_for(ws.recv(), 60), "binary_frame"))
        await ws.send('{"type": "ping", "request_id": "still-here"}')
        replies.append(("ping after all of it", await asyncio.wait_for(ws.recv(), 60), None))
    return replies


async def flood(url: str) -> list[dict]:
    """500 messages as fast as possible: most are dropped with rate_limited errors."""
    from websockets.asyncio.client import connect

    async with connect(url) as ws:
        for i in range(500):
            await ws.send(json.dumps({"type": "ping", "request_id": str(i)}))
        replies = []
        try:
            while True:
                replies.append(json.loads(await asyncio.wait_for(ws.recv(), 2.0)))
        except asyncio.TimeoutError:
            pass
        await asyncio.sleep(1.1)  # the bucket refills: served again
        await ws.send('{"type": "ping", "request_id": "after"}')
        replies.append(json.loads(await asyncio.wait_for(ws.recv(), 10)))
    return replies


async def oversize_transport_frame(url: str) -> int | None:
    """A frame over the WebSocket layer's hard limit (4x the message limit): closed with 1009."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    async with connect(url, max_size=None) as ws:
        try:
            await ws.send("x" * (9 << 20))
            await asyncio.wait_for(ws.recv(), 30)
        except ConnectionClosed as exc:
            return exc.rcvd.code if exc.rcvd else None
    return None


def http(method: str, url: str, body: bytes | None = None) -> tuple[int, dict]:
    request = urllib.request.Request(url, data=body, method=method,
                                     headers={"content-type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


REST_CASES = [
    ("REST garbage body", "POST", "/jobs", b"\x00garbage", 400, "invalid_json"),
    ("REST missing fields", "POST", "/jobs", b'{"kind": "solve"}', 422, "invalid_message"),
    ("REST XML bomb", "POST", "/jobs", json.dumps({"kind": "simulate", "scene_xml": BILLION_LAUGHS}).encode(),
     422, "invalid_scene"),
    ("REST traversal", "POST", "/jobs", b'{"kind": "simulate", "scene_path": "../../etc/passwd"}', 400,
     "path_outside_root"),
    ("REST oversize body", "POST", "/jobs", b" " * (3 << 20), 413, "message_too_large"),
    ("REST forged job id", "GET", "/jobs/..%2F..%2Fetc%2Fpasswd", None, 404, "not_found"),
    ("REST artefact traversal", "GET", "/jobs/" + "a" * 32 + "/..%2F..%2Fjob.json", None, 404, "not_found"),
]


def test_hostile_input_while_other_clients_jobs_complete(live_server):
    from dejaview.inference.solve import solve
    from dejaview.inference.solve import SolveParams
    from dejaview.scene import Scene
    from dejaview.sim.simulate import simulate

    url = live_server.ws_url

    async def everything():
        victims = [asyncio.create_task(submit_job(url, "solve", scene_xml=THROW_XML, timeout=300,
                                                  overrides={"iterations": 4})),
                   asyncio.create_task(submit_job(url, "simulate", scene_xml=BALL_XML, timeout=300))]
        await asyncio.sleep(0.05)
        hostile = await asyncio.gather(hostile_session(url), flood(url), oversize_transport_frame(url))
        rest = [(name, *await asyncio.to_thread(http, method, live_server.http_url + path, body), status, code)
                for name, method, path, body, status, code in REST_CASES]
        return await asyncio.gather(*victims), hostile, rest

    (solved, simulated), (replies, flooded, close_code), rest = asyncio.run(everything())

    kinds = set()
    for name, reply, code in replies:
        kinds.add(name)
        if name == "ping after all of it":
            assert json.loads(reply) == {"type": "pong", "request_id": "still-here"}
        elif code is None:  # bare-text mode
            assert reply.startswith("error: ") and "\n" not in reply, (name, reply)
        else:
            msg = json.loads(reply)
            assert msg["type"] == "error" and msg["code"] == code, (name, msg)
            assert msg["message"] and "\n" not in msg["message"], (name, msg)
    codes = [m.get("code") for m in flooded if m["type"] == "error"]
    assert codes and set(codes) == {"rate_limited"}
    assert 50 <= sum(m["type"] == "pong" for m in flooded) < 500  # the burst, not the flood
    assert flooded[-1] == {"type": "pong", "request_id": "after"}
    kinds.add("flood")
    # 1009 "message too big"; a client still writing the frame may see the close as a reset instead
    assert close_code in (1009, 1006, None)
    kinds.add("frame over the transport limit")
    for name, status, body, want_status, want_code in rest:
        assert (status, body["code"]) == (want_status, want_code), (name, status, body)
        kinds.add(name)
    assert len(kinds) >= 40

    # the other clients' jobs finished, with the same results as the library gives directly
    assert simulated.state == "done" and solved.state == "done"
    ball = Scene.from_string(BALL_XML, base_dir=FIXTURES)
    assert simulated.csv == simulate(ball).csv()
    direct = solve(Scene.from_string(THROW_XML, base_dir=FIXTURES), SolveParams(iterations=4))
    assert solved.result["loss"] == pytest.approx(direct.loss, rel=1e-9)
    assert solved.result["initial_state"]["linear_velocity"] == pytest.approx(
        direct.initial_state["linear_velocity"], rel=1e-9)
    health = wait_healthy(live_server.http_url, timeout=10)
    assert health["workers_ready"] == 2 and live_server.process.poll() is None
