"""Access (protocol.md, "Access"): Origin and Host checks, the token on REST, on the WebSocket's
JSON protocol and on its bare-text mode, the viewer's pages with a token; then the real
``dejaview serve`` off loopback (a generated token) and ``dejaview client`` carrying it."""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys

import anyio
import pytest
from starlette.websockets import WebSocketDisconnect

from dejaview.sim.trajectory_csv import HEADER
from dejaview.server.access import host_name, is_loopback, normalize_origin
from dejaview.server.client import ClientError, run_job, with_token
from dejaview.server.config import ServerConfig
from dejaview.server.local import LocalServer, free_port

from .conftest import FIXTURES, http, receive, until_done

TOKEN = "s3cret-Token_42"
EVIL = "http://evil.example"
BALL_XML = (FIXTURES / "ball.xml").read_text()


def closed_code(ws, timeout: float = 10.0) -> int:
    """The close code of a TestClient WebSocket that the server closes without a message
    (fails, rather than waits for ever, when a message comes or nothing does)."""
    async def get():
        with anyio.fail_after(timeout):
            return await ws._send_rx.receive()

    message = ws.portal.call(get)
    assert message["type"] == "websocket.close", message
    return message["code"]


# ------------------------------------------------------------------ helpers
def test_origins_and_hosts_are_normalized():
    assert normalize_origin("HTTP://Example.com:80") == "http://example.com"
    assert normalize_origin("https://example.com:443/") == "https://example.com"
    assert normalize_origin("http://[::1]:8765") == "http://[::1]:8765"
    for bad in ("null", "file://", "example.com", "http://a/b", "ftp://x", "http://x:99999", "http://u@x"):
        assert normalize_origin(bad) is None, bad
    assert host_name("127.0.0.1:8765") == "127.0.0.1" and host_name("[::1]:80") == "::1"
    assert host_name("LocalHost") == "localhost"
    assert all(is_loopback(h) for h in ("127.0.0.1", "127.3.2.1", "::1", "[::1]", "localhost"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "::", "192.168.1.20", "my-laptop.local"))


def test_config_checks_origins_and_token(tmp_path):
    config = ServerConfig(tmp_path, tmp_path / "r", allow_origins=("HTTP://Quest.local:8765", "null"))
    assert config.allow_origins == ("http://quest.local:8765", "null")
    with pytest.raises(ValueError, match="is not an origin"):
        ServerConfig(tmp_path, tmp_path / "r", allow_origins=("quest.local",))
    with pytest.raises(ValueError, match="token"):
        ServerConfig(tmp_path, tmp_path / "r", token="two words")


# ------------------------------------------------------------------ Origin and Host
def test_rest_refuses_other_origins(make_client):
    client = make_client(allow_origins=("https://viewer.example",))
    assert client.get("/scenes").status_code == 200  # no Origin: not a browser
    for origin in ("http://testserver", "https://viewer.example", "https://viewer.example:443"):
        assert client.get("/scenes", headers={"Origin": origin}).status_code == 200, origin
    for origin in (EVIL, "null", "http://testserver:8080", "https://testserver", "garbage"):
        response = client.post("/jobs", json={"kind": "simulate", "scene_path": "ball.xml"},
                               headers={"Origin": origin})
        assert response.status_code == 403, origin
        assert response.json()["code"] == "forbidden_origin" and "may not use this server" in response.json()["message"]
    assert client.get("/health", headers={"Origin": EVIL}).status_code == 403
    assert client.get("/jobs/" + "0" * 32, headers={"Origin": EVIL}).json()["code"] == "forbidden_origin"


def test_websocket_handshakes_from_other_origins_are_refused(make_client):
    client = make_client(allow_origins=("http://quest.local:8765",))
    for origin in (EVIL, "null"):
        with pytest.raises(WebSocketDisconnect) as info:  # refused before the accept: HTTP 403
            with client.websocket_connect("/ws", headers={"Origin": origin}):
                pass
        assert info.value.code == 1008
    for origin in ("http://testserver", "http://quest.local:8765", None):
        with client.websocket_connect("/ws", headers={"Origin": origin} if origin else {}) as ws:
            ws.send_text('{"type": "ping", "request_id": "p"}')
            assert receive(ws) == {"type": "pong", "request_id": "p"}


def test_a_loopback_server_refuses_foreign_host_names(make_client):
    """DNS rebinding: a page of evil.example whose name resolves to 127.0.0.1 is same-origin with
    itself, so the Host header is what tells it apart."""
    client = make_client(allowed_hosts=("localhost", "127.0.0.1", "::1"))
    client.base_url = "http://127.0.0.1:8765"
    assert client.get("/scenes").status_code == 200
    assert client.get("/scenes", headers={"Host": "localhost:8765"}).status_code == 200
    response = client.get("/scenes", headers={"Host": "evil.example:8765", "Origin": "http://evil.example:8765"})
    assert response.status_code == 403 and response.json()["code"] == "forbidden_host"


# ------------------------------------------------------------------ token, REST
def test_rest_needs_the_token(make_client):
    client = make_client(token=TOKEN)
    job = {"kind": "simulate", "scene_path": "ball.xml"}
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": TOKEN},
                    {"Authorization": f"Basic {TOKEN}"}, {"Authorization": f"Bearer {TOKEN}x"}):
        for method, path in (("GET", "/scenes"), ("GET", "/jobs/" + "0" * 32), ("POST", "/jobs"),
                             ("DELETE", "/jobs/" + "0" * 32), ("GET", "/docs"), ("GET", "/"),
                             ("GET", "/static/app.js"), ("GET", "/files/ball.xml"),
                             ("GET", "/jobs/" + "0" * 32 + "/result.json"), ("GET", "/jobs/" + "0" * 32 + "/model")):
            response = client.request(method, path, headers=headers, json=job if method == "POST" else None)
            assert response.status_code == 401, (method, path, headers)
            assert response.json()["code"] == "unauthorized"
            assert response.headers["www-authenticate"].startswith("Bearer")
    # nothing was run: a refused request leaves no job behind
    assert client.get("/health").json()["queued"] == 0 and client.get("/health").json()["running"] == 0
    auth = {"Authorization": f"Bearer {TOKEN}"}
    response = client.post("/jobs", json=job, headers=auth)
    assert response.status_code == 202
    job_id = response.json()["job_id"]
    assert client.get(f"/jobs/{job_id}", headers=auth).status_code == 200
    # the query form is for GET (a browser's page and links) and the WebSocket, not for changes
    assert client.get(f"/jobs/{job_id}?token={TOKEN}").status_code == 200
    assert client.post(f"/jobs?token={TOKEN}", json=job).status_code == 401
    assert client.delete(f"/jobs/{job_id}?token={TOKEN}").status_code == 401


def test_health_needs_no_token(make_client):
    client = make_client(token=TOKEN)
    body = client.get("/health").json()
    assert body["status"] == "ok"
    assert client.head("/health").status_code in (200, 405)  # never 401
    assert client.post("/health").status_code == 401  # only reading it is free


def test_a_token_on_loopback_is_optional_unless_given(make_client):
    open_client = make_client()
    assert open_client.get("/scenes").status_code == 200
    assert open_client.get("/scenes", headers={"Authorization": "Bearer whatever"}).status_code == 200


# ------------------------------------------------------------------ token, WebSocket
def test_websocket_without_the_right_token_is_closed_with_4401(make_client):
    client = make_client(token=TOKEN)
    for url in ("/ws", "/ws?token=wrong", f"/ws?token={TOKEN}x", "/ws?token="):
        with client.websocket_connect(url) as ws:
            assert closed_code(ws) == 4401, url  # and nothing else came first
    # nor does a frame sent anyway get anywhere (JSON or bare text)
    for frame in ('{"type": "submit", "kind": "simulate", "scene_path": "ball.xml"}', "drop.xml"):
        with client.websocket_connect("/ws") as ws:
            ws.send_text(frame)
            assert closed_code(ws) == 4401
    assert client.get("/health").json()["queued"] == 0 and client.get("/health").json()["running"] == 0


def test_websocket_json_and_bare_text_with_the_token(make_client):
    client = make_client(token=TOKEN)
    with client.websocket_connect(f"/ws?token={TOKEN}") as ws:
        ws.send_text(json.dumps({"type": "submit", "kind": "simulate", "scene_path": "ball.xml"}))
        messages = until_done(ws)
        assert [m["type"] for m in messages][-2:] == ["trajectory", "done"]
        ws.send_text("drop.xml")  # the original Unreal client's bare-text mode
        csv_text = receive(ws)
        assert isinstance(csv_text, str) and csv_text.startswith(",".join(HEADER))
    # the Authorization header works on the WebSocket too, for clients that can set one
    with client.websocket_connect("/ws", headers={"Authorization": f"Bearer {TOKEN}"}) as ws:
        ws.send_text('{"type": "ping"}')
        assert receive(ws) == {"type": "pong"}


# ------------------------------------------------------------------ the viewer with a token
def test_the_viewer_loads_with_the_token_in_its_url(make_client):
    client = make_client(token=TOKEN)
    page = client.get(f"/?token={TOKEN}")
    assert page.status_code == 200 and page.headers["referrer-policy"] == "no-referrer"
    scripts = re.findall(r'(?:src|href)="(static/[^"]+)"', page.text)
    assert sorted(scripts) == [f"static/app.js?token={TOKEN}", f"static/style.css?token={TOKEN}"]
    for url in scripts:
        assert client.get("/" + url).status_code == 200
    assert client.get("/static/app.js").status_code == 401
    # without a token the page is the plain one
    plain = make_client().get("/").text
    assert 'src="static/app.js"' in plain and "token" not in plain


def test_the_viewer_source_sends_the_token():
    """The browser side (web/src, built into static/app.js): REST calls carry a Bearer header and
    the WebSocket URL a ?token=, both from the page's own URL; tests/web drives it for real."""
    from dejaview.server.viewer import STATIC_DIR

    bundle = (STATIC_DIR / "app.js").read_text()
    assert "Bearer " in bundle and "searchParams.set(\"token\"" in bundle.replace("'", '"')
    assert "4401" in bundle


# ------------------------------------------------------------------ the real server off loopback
async def ws_close_code(url: str, frame: str, origin: str | None = None):
    """What a real WebSocket client meets: ('closed', code) or ('refused', HTTP status) or
    ('message', text)."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidStatus

    try:
        async with connect(url, origin=origin, open_timeout=30) as ws:
            await ws.send(frame)
            return "message", await asyncio.wait_for(ws.recv(), 60)
    except InvalidStatus as exc:
        return "refused", exc.response.status_code
    except ConnectionClosed as exc:
        return "closed", exc.rcvd.code if exc.rcvd else None


def test_serve_off_loopback_generates_a_token_and_requires_it(live_root, tmp_path):
    port = free_port("0.0.0.0")
    env_token = os.environ.pop("DEJAVIEW_TOKEN", None)
    server = LocalServer(live_root, tmp_path / "results", host="0.0.0.0", port=port,
                         log_path=tmp_path / "serve.log", workers=1, log_level="warning")
    try:
        server.start()
        log = server.log_path.read_text()
        tokens = re.findall(r"generated one \(given once, here\): (\S+)", log)
        assert len(tokens) == 1, log
        token = tokens[0]
        assert log.count(token) == 3  # the line that gives it, and the two URLs that use it
        base, ws = f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}/ws"
        assert http("GET", f"{base}/health")[0] == 200
        status, body = http("POST", f"{base}/jobs", body={"kind": "simulate", "scene_path": "drop.xml"})
        assert (status, body["code"]) == (401, "unauthorized")
        assert http("GET", f"{base}/scenes", token="nope")[0] == 401
        assert http("GET", f"{base}/scenes", token=token)[0] == 200
        status, body = http("GET", f"{base}/scenes", token=token, origin=EVIL)
        assert (status, body["code"]) == (403, "forbidden_origin")

        async def sockets():
            return await asyncio.gather(
                ws_close_code(ws, '{"type": "ping"}'),
                ws_close_code(ws, "drop.xml"),
                ws_close_code(with_token(ws, "nope"), "drop.xml"),
                ws_close_code(with_token(ws, token), '{"type": "ping"}'),
                ws_close_code(with_token(ws, token), "drop.xml"),
                ws_close_code(with_token(ws, token), '{"type": "ping"}', origin=EVIL),
                ws_close_code(with_token(ws, token), '{"type": "ping"}', origin=f"http://127.0.0.1:{port}"))

        json_none, bare_none, bare_wrong, json_ok, bare_ok, evil, own = asyncio.run(sockets())
        assert json_none == bare_none == bare_wrong == ("closed", 4401)
        assert json_ok == ("message", '{"type":"pong"}')
        assert bare_ok[0] == "message" and bare_ok[1].startswith(",".join(HEADER))
        assert evil == ("refused", 403)
        assert own == ("message", '{"type":"pong"}')

        # dejaview client: the token from --token or DEJAVIEW_TOKEN, a one-line error without it
        def client(*args, env=None):
            return subprocess.run([sys.executable, "-m", "dejaview", "client", "drop.xml", "--scene-path",
                                   "--kind", "simulate", "--url", ws, "-o", tmp_path / "out", "-q", *args],
                                  capture_output=True, text=True, timeout=120, env={**os.environ, **(env or {})})
        refused = client()
        assert refused.returncode != 0
        assert refused.stderr.strip().count("\n") == 0 and "4401" in refused.stderr and "token" in refused.stderr
        assert client("--token", token).returncode == 0
        ok = client(env={"DEJAVIEW_TOKEN": token})
        assert ok.returncode == 0, ok.stderr
        assert (tmp_path / "out" / "trajectory.csv").read_text().startswith(",".join(HEADER))
        with pytest.raises(ClientError, match="4401"):
            run_job(ws, "simulate", scene_path="drop.xml", token="wrong", timeout=60)
    finally:
        server.stop()
        if env_token is not None:
            os.environ["DEJAVIEW_TOKEN"] = env_token


def test_serve_with_a_bad_allowed_origin_says_so(tmp_path):
    result = subprocess.run([sys.executable, "-m", "dejaview", "serve", "--results-dir", tmp_path / "r",
                             "--allow-origin", "quest.local"], capture_output=True, text=True, timeout=60)
    assert result.returncode != 0
    assert result.stderr.strip().count("\n") == 0 and "is not an origin" in result.stderr, result.stderr
