"""The viewer against a server that needs a token (opened as ``/?token=...``), and a page of another
site that tries to drive a server on the user's machine (protocol.md, "Access"), in chromium."""

from __future__ import annotations

import pytest

from dejaview.server.local import LocalServer

from .conftest import load_scene, needs_browser, state

pytestmark = needs_browser
TOKEN = "viewer-token-0123456789"


@pytest.fixture(scope="module")
def token_server(web_root, tmp_path_factory):
    base = tmp_path_factory.mktemp("token")
    server = LocalServer(web_root, base / "results", log_path=base / "serve.log", workers=1, executor="thread",
                         rate=50, log_level="warning", token=TOKEN)
    server.start()
    yield server
    server.stop()


def test_the_viewer_works_with_a_token_from_its_url(page, token_server):
    assert page.goto(token_server.http_url + "/").status == 401  # no token, no page
    page.goto(f"{token_server.http_url}/?token={TOKEN}")
    page.wait_for_function("window.dejaview && window.dejaview.state().connected")
    page.wait_for_function("document.querySelectorAll('#scene-list option').length > 0")  # GET /scenes
    loaded = load_scene(page, "scenes/toss.xml")  # the scene and its mesh through GET /files
    assert loaded["objects"] == ["floor", "table", "cube", "ball"]
    page.evaluate("window.dejaview.run('simulate')")
    page.wait_for_function("window.dejaview.state().jobs.some(j => j.state === 'done')", timeout=120_000)
    assert state(page)["trajectoryObjects"], state(page)["notifications"]
    assert not [n for n in state(page)["notifications"] if n["kind"] == "error"]


def test_a_wrong_token_is_reported_once_not_retried(page, token_server):
    page.goto(f"{token_server.http_url}/?token={TOKEN}")
    page.wait_for_function("window.dejaview && window.dejaview.state().connected")
    # the same page with a token the server refuses: its WebSocket is closed with 4401
    page.evaluate("""() => new Promise((resolve) => {
        const ws = new WebSocket(location.origin.replace('http', 'ws') + '/ws?token=wrong');
        ws.onclose = (e) => { window.closeCode = e.code; resolve(); };
    })""")
    assert page.evaluate("window.closeCode") == 4401


def test_a_page_of_another_site_cannot_drive_the_server(page, web_server, web_root):
    """A page of http://evil.example (served here by Playwright, no network) tries the server on
    127.0.0.1 (the default one, no token): its WebSocket handshake is refused, no job is submitted."""
    jobs = web_root.parent / "results" / "jobs"
    before = sorted(p.name for p in jobs.iterdir())
    page.route("http://evil.example/**", lambda route: route.fulfill(
        status=200, content_type="text/html", body="<!doctype html><title>evil</title>"))
    page.goto("http://evil.example/")
    outcome = page.evaluate("""(base) => new Promise((resolve) => {
        const socket = new WebSocket(base.replace('http', 'ws') + '/ws');
        socket.onopen = () => {
            socket.send(JSON.stringify({type: 'submit', kind: 'simulate', scene_path: 'scenes/toss.xml'}));
            setTimeout(() => resolve('open'), 2000);
        };
        socket.onclose = (e) => resolve('closed ' + e.code);
    })""", web_server.http_url)
    assert outcome == "closed 1006", outcome  # the handshake got HTTP 403: no connection at all
    assert sorted(p.name for p in jobs.iterdir()) == before
    # the same from the server's own page works (the viewer tests run jobs through it)
    page.goto(web_server.http_url + "/")
    page.wait_for_function("window.dejaview && window.dejaview.state().connected")
