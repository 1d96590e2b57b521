"""WebXR with an emulated headset: iwer (Meta's Immersive Web Emulation Runtime, from npm, its
browser build copied to tests/web/assets by ``npm run build``) installed into the page before the
viewer starts. Enter VR through the button, grab the ball with the right controller's trigger,
carry it, let go: the scene's set-up pose follows; the squeeze button starts a solve."""

from __future__ import annotations

import pytest

from .conftest import ASSETS, load_scene, needs_browser, open_viewer, state

pytestmark = needs_browser

INSTALL = """
window.__xr = new IWER.XRDevice(IWER.metaQuest3);
window.__xr.installRuntime({ forceInstall: true });
"""


def controller(page, side: str, code: str):
    return page.evaluate(f"(() => {{ const c = window.__xr.controllers[{side!r}]; {code} }})()")


def controller_at(page, index: int, xyz) -> None:
    """Wait until the viewer sees controller ``index`` at ``xyz`` (XR frame, y up)."""
    page.wait_for_function(f"(p => p && Math.hypot(p[0] - {xyz[0]}, p[1] - {xyz[1]}, p[2] - {xyz[2]}) < 1e-3)"
                           f"(window.dejaview.state().xr.controllers[{index}])")


def test_enter_vr_and_grab_an_object(page, web_server, artifacts):
    page.add_init_script(path=str(ASSETS / "iwer.min.js"))
    page.add_init_script(INSTALL)
    open_viewer(page, web_server)
    load_scene(page, "scenes/toss.xml")
    page.wait_for_function("document.getElementById('VRButton').textContent === 'ENTER VR'")
    page.click("#VRButton")
    page.wait_for_function("window.dejaview.state().xr.presenting")
    assert state(page)["xr"]["sessions"] == 1
    page.wait_for_function("window.dejaview.state().xr.connected === 2")  # both controllers tracked

    # the ball is at (0.5, 0.3, 0.3) in the z-up scene: (0.5, 0.3, -0.3) in the y-up XR frame;
    # hold the right controller 30 cm in front of it (+z), pointing at it (-z, the default)
    controller(page, "right", "c.position.set(0.5, 0.3, 0.0); c.quaternion.set(0, 0, 0, 1);")
    controller_at(page, 1, (0.5, 0.3, 0.0))
    controller(page, "right", "c.updateButtonValue('trigger', 1);")
    page.wait_for_function("window.dejaview.state().xr.grabs === 1")
    assert state(page)["xr"]["holding"] == [None, "ball"]

    # carry it 20 cm along +x (the scene's x) and 10 cm up (the scene's z), then let go
    controller(page, "right", "c.position.set(0.7, 0.4, 0.0);")
    controller_at(page, 1, (0.7, 0.4, 0.0))
    controller(page, "right", "c.updateButtonValue('trigger', 0);")
    page.wait_for_function("window.dejaview.state().xr.releases === 1")
    s = state(page)
    assert s["setup"]["ball"] == pytest.approx([0.7, 0.3, 0.4], abs=0.02), s["setup"]["ball"]
    assert s["positions"]["ball"] == pytest.approx(s["setup"]["ball"], abs=1e-6)
    page.screenshot(path=artifacts / "5-vr-grabbed.png")

    # squeeze: a solve (heatmap off and one iteration, to keep it short)
    page.evaluate("window.dejaview.setSettings({heatmap: false, iterations: 1})")
    controller(page, "right", "c.updateButtonValue('squeeze', 1);")
    page.wait_for_function("window.dejaview.state().xr.solves === 1")
    controller(page, "right", "c.updateButtonValue('squeeze', 0);")
    page.wait_for_function("window.dejaview.state().jobs.some(j => j.state === 'done')", timeout=120_000)
    assert state(page)["jobs"][0]["kind"] == "solve"
