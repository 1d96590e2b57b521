"""Fixtures of the web viewer tests: one real ``dejaview serve`` over a tiny scene root, and
Debian's chromium driven by Playwright (``executable_path``; no browser is ever downloaded).

Screenshots go to ``$DEJAVIEW_TEST_ARTIFACTS/web`` (default ``out/test-artifacts/web`` in the
repository). Without ``/usr/bin/chromium`` (``apt-get install chromium``; ``scripts/setup-browser``
installs it when it can) or the ``playwright`` package the tests are skipped, saying which.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from dejaview.server.local import LocalServer

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "tests" / "fixtures" / "web"
ASSETS = Path(__file__).resolve().parent / "assets"
CHROMIUM = Path(os.environ.get("DEJAVIEW_CHROMIUM", "/usr/bin/chromium"))
# WebGL in headless chromium without a GPU: ANGLE on SwiftShader
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def _why_no_browser() -> str | None:
    if not CHROMIUM.is_file():
        return f"{CHROMIUM} is missing (apt-get install chromium; scripts/setup-browser does it as root)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the playwright package is missing (pip install -c constraints.txt -e '.[test]')"
    return None


WHY_NO_BROWSER = _why_no_browser()
needs_browser = pytest.mark.skipif(WHY_NO_BROWSER is not None, reason=f"browser tests: {WHY_NO_BROWSER}")


@pytest.fixture(scope="session")
def artifacts() -> Path:
    base = Path(os.environ.get("DEJAVIEW_TEST_ARTIFACTS", REPO / "out" / "test-artifacts"))
    out = base / "web"
    out.mkdir(parents=True, exist_ok=True)
    return out


# examples the viewer tests load as they ship (paths inside the examples folder, kept in the root)
EXAMPLES = ("scenes/box_tossed_tracked.xml", "meshes/box.obj", "packings/box.spheres")


@pytest.fixture(scope="session")
def web_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("web") / "root"
    shutil.copytree(FIXTURES, root)
    for name in EXAMPLES:
        (root / "examples" / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(REPO / "examples" / name, root / "examples" / name)
    return root


@pytest.fixture(scope="session")
def web_server(web_root):
    """One real ``dejaview serve`` (one process worker) for the browser tests."""
    base = web_root.parent
    server = LocalServer(web_root, base / "results", log_path=base / "serve.log", workers=1,
                         rate=50, log_level="warning")
    server.start()
    server.wait_workers()
    yield server
    server.stop()


@pytest.fixture(scope="module")
def browser():
    """Chromium under playwright's sync API, per module: the sync API runs an asyncio loop in this
    thread while it is open, so a session-wide browser broke every later ``asyncio.run`` of the
    same process (the server tests, when a web module ran before them: ``pytest -n``, or any order)."""
    if WHY_NO_BROWSER:
        pytest.skip(f"browser tests: {WHY_NO_BROWSER}")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield browser
        browser.close()


@pytest.fixture
def page(browser, web_server):
    """A fresh page; page errors (uncaught exceptions) fail the test."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.set_default_timeout(30_000)
    yield page
    context.close()
    assert not errors, errors


def open_viewer(page, server) -> None:
    page.goto(server.http_url + "/")
    page.wait_for_function("window.dejaview && window.dejaview.state().connected")
    page.wait_for_function("document.querySelectorAll('#scene-list option').length > 0")


def load_scene(page, path: str) -> dict:
    """Pick ``path`` in the scene list and press Load (the UI, not a hook); the state once loaded."""
    loaded = "window.dejaview.state().notifications.filter(n => n.text.startsWith('loaded ')).length"
    before = page.evaluate(loaded)
    page.select_option("#scene-list", path)
    page.click("#load-scene")
    # the "loaded" notice comes once every object is complete (meshes, then packings, the
    # target ghost and the start area), not when the last mesh is in
    page.wait_for_function(
        f"(s => s.origin === {path!r} && s.objects.length && s.meshesLoaded === s.objects.length"
        f" && {loaded} > {before})(window.dejaview.state())")
    return state(page)


def state(page) -> dict:
    return page.evaluate("window.dejaview.state()")
