"""Fixtures of the server tests: a scene root with hostile corners, apps under TestClient (thread
workers) and one real ``dejaview serve`` process (process workers) shared by the live tests."""

from __future__ import annotations

import json
import shutil
import urllib.error
import urllib.request
from pathlib import Path

import anyio
import pytest
from fastapi.testclient import TestClient

from dejaview.server.app import create_app
from dejaview.server.local import LocalServer

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "server"


def make_scene_root(base: Path) -> Path:
    """``base/root``: the fixtures plus a symlinked scene and a symlinked folder that lead to
    ``base/outside`` (a valid scene and mesh the server must never read)."""
    root = base / "root"
    shutil.copytree(FIXTURES, root)
    outside = base / "outside"
    outside.mkdir()
    shutil.copy(FIXTURES / "drop.xml", outside / "secret.xml")
    shutil.copy(FIXTURES / "meshes" / "cube.obj", outside / "secret.obj")
    (root / "escape.xml").symlink_to(outside / "secret.xml")
    (root / "linked").symlink_to(outside, target_is_directory=True)
    return root


@pytest.fixture
def scene_root(tmp_path) -> Path:
    return make_scene_root(tmp_path)


@pytest.fixture
def make_client(tmp_path, scene_root):
    """``make_client(**config)`` -> a started TestClient (thread workers); closed at the end."""
    clients = []

    def make(**settings):
        settings = {"scene_root": scene_root, "results_dir": tmp_path / "results", "workers": 2,
                    "executor": "thread", "progress_interval_s": 0.0, **settings}
        client = TestClient(create_app(**settings))
        client.__enter__()
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.__exit__(None, None, None)


@pytest.fixture
def client(make_client):
    return make_client()


def http(method: str, url: str, token: str | None = None, body: dict | None = None,
         origin: str | None = None) -> tuple[int, dict]:
    headers = {"content-type": "application/json"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    if origin:
        headers["Origin"] = origin
    request = urllib.request.Request(url, method=method, headers=headers,
                                     data=json.dumps(body).encode() if body is not None else None)
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def receive(ws, timeout: float = 60.0):
    """The next message of a TestClient WebSocket: a dict for JSON text, else the raw text."""
    async def get():
        with anyio.fail_after(timeout):
            return await ws._send_rx.receive()

    message = ws.portal.call(get)
    assert message["type"] == "websocket.send", message
    text = message["text"]
    try:
        return json.loads(text)
    except ValueError:
        return text


def until_done(ws, job_id: str | None = None, timeout: float = 60.0) -> list:
    """Messages up to and including ``done`` (of ``job_id`` if given)."""
    out = []
    while True:
        msg = receive(ws, timeout)
        out.append(msg)
        if isinstance(msg, dict) and msg.get("type") == "done" and (job_id is None or msg["job_id"] == job_id):
            return out


def types(messages) -> list[str]:
    return [m["type"] if isinstance(m, dict) else "text" for m in messages]


@pytest.fixture(scope="session")
def live_root(tmp_path_factory) -> Path:
    return make_scene_root(tmp_path_factory.mktemp("live"))


@pytest.fixture(scope="session")
def live_server(live_root, tmp_path_factory):
    """One real ``dejaview serve`` (2 process workers) for the whole session."""
    base = live_root.parent
    server = LocalServer(live_root, base / "results", log_path=base / "serve.log", workers=2,
                         queue_size=64, rate=50, log_level="warning")
    server.start()
    server.wait_workers()
    yield server
    server.stop()
