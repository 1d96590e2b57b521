"""Live answers in the viewer (headless chromium, a real ``dejaview serve``): with "live" ticked, a
scene without a model says so (Train); once its model is in the server's models folder, dragging the
target with the mouse updates the heatmap and the start-point cloud from ``live`` answers. The time
from the drag to the new heatmap drawn is measured in the page and printed, never asserted."""

from __future__ import annotations

import shutil

import pytest

from dejaview.server.local import LocalServer

from .conftest import REPO, load_scene, needs_browser, open_viewer, state
from .test_viewer import drag_gizmo_x

pytestmark = needs_browser
pytest.importorskip("zuko", reason="the amortised extra (pip install 'dejaview[amortised]')")

SCENE = REPO / "tests" / "fixtures" / "server" / "throw.xml"


@pytest.fixture(scope="module")
def live_server(tmp_path_factory):
    base = tmp_path_factory.mktemp("web-live")
    (base / "root" / "scenes").mkdir(parents=True)
    shutil.copy(SCENE, base / "root" / "scenes" / "throw.xml")
    server = LocalServer(base / "root", base / "results", log_path=base / "serve.log", workers=1,
                         log_level="warning")
    server.start()
    server.wait_workers()
    yield server
    server.stop()


@pytest.fixture
def live_page(browser, live_server):
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.set_default_timeout(60_000)
    yield page
    context.close()
    assert not errors, errors


def train_into(server) -> str:
    """A tiny model of the scene, where the server looks for it; its fingerprint."""
    from dejaview.inference.amortised import train
    from dejaview.inference.params import TrainParams
    from dejaview.scene import Scene
    from dejaview.server.live import model_path

    model = train(Scene.from_xml(SCENE), TrainParams(simulations=400, epochs=15, patience=5, transforms=2,
                                                     hidden=(32, 32), batch=128, lr=3e-3))
    model.save(model_path(server.results_dir / "models", model.fingerprint))
    return model.fingerprint


def live_state(page) -> dict:
    return page.evaluate("window.dejaview.state().live")


def test_dragging_the_target_updates_the_live_heatmap(live_page, live_server, artifacts):
    page = live_page
    open_viewer(page, live_server)
    load_scene(page, "scenes/throw.xml")
    page.check("#live")
    page.wait_for_function("window.dejaview.state().live.error !== null")
    assert live_state(page)["error"]["code"] == "no_model"
    assert "Train" in page.inner_text("#live-status")

    train_into(live_server)
    page.click("#select-target")
    assert state(page)["selected"] == "#target" and state(page)["gizmoAttached"]
    drag_gizmo_x(page, "#target", 0.03)  # the first answer, from the model now in place
    page.wait_for_function("(s => s.answers >= 1 && !s.inFlight)(window.dejaview.state().live)")
    first = live_state(page)
    assert first["error"] is None and first["samples"] > 0 and state(page)["heatmapShown"]
    before = first["probability"]
    assert abs(sum(map(sum, before)) - 1.0) < 1e-6

    drag_gizmo_x(page, "#target", -0.08)
    page.wait_for_function(f"(s => s.answers > {first['answers']} && !s.inFlight)(window.dejaview.state().live)")
    after = live_state(page)
    assert after["probability"] != before  # the heatmap follows the target
    assert state(page)["heatmapCells"] == [16, 16]
    page.screenshot(path=artifacts / "live-heatmap.png")
    print(f"live: {after['answers']} answers while dragging; move to heatmap drawn (ms, in the page): "
          f"{[round(v) for v in after['latencies']]}")
