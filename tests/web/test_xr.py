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


def press(page, name: str) -> None:
    """Aim the right controller at the VR menu's button ``name`` and pull the trigger."""
    presses = len(state(page)["xr"]["menuPresses"])
    aim = page.evaluate(f"window.dejaview.vrMenuAim({name!r})")
    (x, y, z), (qx, qy, qz, qw) = aim["position"], aim["quaternion"]
    controller(page, "right", f"c.position.set({x}, {y}, {z}); c.quaternion.set({qx}, {qy}, {qz}, {qw});")
    controller_at(page, 1, (x, y, z))
    controller(page, "right", "c.updateButtonValue('trigger', 1);")
    page.wait_for_function(f"window.dejaview.state().xr.menuPresses.length === {presses + 1}")
    controller(page, "right", "c.updateButtonValue('trigger', 0);")
    assert state(page)["xr"]["menuPresses"][-1] == name


def grab_and_move(page, at, by) -> None:
    """Point the right controller at ``at`` (scene frame, z up) from 30 cm in front, pull the trigger,
    carry it by ``by`` (XR frame) and let go."""
    grabs, releases = state(page)["xr"]["grabs"], state(page)["xr"]["releases"]
    x, y, z = at[0], at[2], -at[1] + 0.3  # the XR frame is y up
    controller(page, "right", f"c.position.set({x}, {y}, {z}); c.quaternion.set(0, 0, 0, 1);")
    controller_at(page, 1, (x, y, z))
    controller(page, "right", "c.updateButtonValue('trigger', 1);")
    page.wait_for_function(f"window.dejaview.state().xr.grabs === {grabs + 1}")
    to = (x + by[0], y + by[1], z + by[2])
    controller(page, "right", f"c.position.set({to[0]}, {to[1]}, {to[2]});")
    controller_at(page, 1, to)
    controller(page, "right", "c.updateButtonValue('trigger', 0);")
    page.wait_for_function(f"window.dejaview.state().xr.releases === {releases + 1}")


def test_vr_menu_timed_targets_and_objects(page, web_server, artifacts):
    """The VR menu above the left controller: add a timed target in front of the eyes, grab it and
    move it, shift its time, delete it; add a box and make it the source; all in the scene's XML."""
    page.add_init_script(path=str(ASSETS / "iwer.min.js"))
    page.add_init_script(INSTALL)
    open_viewer(page, web_server)
    load_scene(page, "scenes/toss.xml")
    page.wait_for_function("document.getElementById('VRButton').textContent === 'ENTER VR'")
    page.click("#VRButton")
    page.wait_for_function("window.dejaview.state().xr.connected === 2")
    # the left hand holds the menu in view, below and left of the eyes (at 1.6 m), out of the way of
    # the right hand's pointing straight ahead
    controller(page, "left", "c.position.set(-0.25, 1.35, -0.35); c.quaternion.set(0, 0, 0, 1);")
    controller_at(page, 0, (-0.25, 1.35, -0.35))

    press(page, "add-target")  # a <target time> half a metre in front of the eyes, halfway through
    s = state(page)
    assert len(s["targets"]) == 2 and s["targets"][1]["time"] == pytest.approx(0.1)
    assert s["selected"] == "#target:1" and s["xr"]["menuStatus"] == "target 2: 0.10 s"
    seen = s["targets"][1]["position"]
    page.screenshot(path=artifacts / "vr-menu-target-added.png")

    grab_and_move(page, seen, (0.1, 0.05, 0.0))  # 10 cm along the scene's x, 5 cm up
    moved = state(page)["targets"][1]["position"]
    assert moved == pytest.approx([seen[0] + 0.1, seen[1], seen[2] + 0.05], abs=0.01), (seen, moved)
    press(page, "time-up")
    assert state(page)["targets"][1]["time"] == pytest.approx(0.15)
    xml = page.evaluate("window.dejaview.exportXml()")
    assert 'time="0.15"' in xml
    press(page, "delete-target")
    assert len(state(page)["targets"]) == 1 and 'time="0.15"' not in page.evaluate("window.dejaview.exportXml()")

    press(page, "box")  # a box in front of the eyes, selected: the menu makes it the source
    page.wait_for_function("window.dejaview.state().objects.includes('box1')")
    press(page, "source")
    s = state(page)
    assert s["source"] == "box1" and s["xr"]["menuStatus"] == "box1: the source"
    assert 'source="box1"' in page.evaluate("window.dejaview.exportXml()")
    page.screenshot(path=artifacts / "vr-menu-box-source.png")
