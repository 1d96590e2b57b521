"""Live answers in the viewer (headless chromium, a real ``dejaview serve``): with "live" ticked, a
scene without a model says so (Train); once its model is in the server's models folder, dragging the
target with the mouse updates the heatmap and the start-point cloud from ``live`` answers. The time
from the drag to the new heatmap drawn is measured in the page and printed, never asserted."""

from __future__ import annotations

import shutil

import pytest

from dejaview.server.local import LocalServer

from .conftest import ASSETS, REPO, load_scene, needs_browser, open_viewer, state
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


def test_carrying_the_target_in_vr_asks_while_it_moves(live_page, live_server, artifacts):
    """A WebXR-emulated controller grabs the target and carries it: live answers come while it is
    still held (not only on release), each for where the target is in the scene at that moment."""
    from .test_xr import INSTALL, controller, controller_at

    if not any((live_server.results_dir / "models").glob("*.safetensors")):
        train_into(live_server)
    page = live_page
    page.add_init_script(path=str(ASSETS / "iwer.min.js"))
    page.add_init_script(INSTALL)
    open_viewer(page, live_server)
    load_scene(page, "scenes/throw.xml")
    page.check("#live")
    page.click("#VRButton")
    page.wait_for_function("window.dejaview.state().xr.connected === 2")
    # the target at (0.2, 0.05, 0.25) in the z-up scene: (0.2, 0.25, -0.05) in the y-up XR frame;
    # the right controller 30 cm in front of it, pointing at it
    x, y, z = 0.2, 0.25, -0.05 + 0.3
    controller(page, "right", f"c.position.set({x}, {y}, {z}); c.quaternion.set(0, 0, 0, 1);")
    controller_at(page, 1, (x, y, z))
    controller(page, "right", "c.updateButtonValue('trigger', 1);")
    page.wait_for_function("window.dejaview.state().xr.grabs === 1")
    answers = live_state(page)["answers"]
    page.wait_for_function("!window.dejaview.state().live.inFlight")  # held still: nothing more asked
    for k in range(1, 4):  # carried 3 cm along the scene's x at a time, the trigger held
        controller(page, "right", f"c.position.set({x + 0.03 * k}, {y}, {z});")
        controller_at(page, 1, (x + 0.03 * k, y, z))
        page.wait_for_function(f"(s => s.answers > {answers} && !s.inFlight)(window.dejaview.state().live)")
        answers = live_state(page)["answers"]
    s = state(page)
    assert s["xr"]["releases"] == 0 and s["xr"]["grabs"] == 1  # all of it while held
    assert live_state(page)["error"] is None and s["heatmapShown"]
    page.screenshot(path=artifacts / "vr-live-carried.png")
    controller(page, "right", "c.updateButtonValue('trigger', 0);")
    page.wait_for_function("window.dejaview.state().xr.releases === 1")
