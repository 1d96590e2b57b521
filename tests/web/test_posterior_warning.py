"""The viewer warns when a job's posterior is not to be trusted: result.json's
``posterior.agreement`` says the sampler's independent runs disagree (``dejaview.inference.
posterior_report.rhat``), and says so in words in the Result panel, beside the modes' probabilities
and the inferred physics. The WebSocket is answered by a stand-in for the server (Playwright's
``route_web_socket``), so the test sets the result itself; scenes still load from a real
``dejaview serve``."""

from __future__ import annotations

import json
import re

from .conftest import load_scene, needs_browser, open_viewer, state

pytestmark = needs_browser


START = {"position": [0.01, -0.02, 0.4], "orientation": [1, 0, 0, 0], "linear_velocity": [0.5, 0, 0],
         "angular_velocity": [0, 0, 0]}
MODES = [{"probability": 0.7, "neg_log_posterior": 3.0, "initial_state": START},
         {"probability": 0.3, "neg_log_posterior": 3.8, "initial_state": {**START, "angular_velocity": [0, 0, 4.0]}}]
PHYSICS = {"most_probable": {"friction": 0.42, "restitution": 0.2, "stiffness": 20000.0}, "inferred": ["friction"],
           "intervals": {"friction": {"median": 0.41, "50%": [0.38, 0.45], "90%": [0.3, 0.55]}}}


def fake_server(agreements: list[dict]):
    """A WebSocket handler answering the n-th submit with accepted, a result whose posterior has
    ``agreements[n]`` (the second also two modes and inferred physics), and done."""
    submits = []

    def handler(ws):
        def on_message(text):
            msg = json.loads(text)
            if msg.get("type") != "submit":
                return
            n = len(submits)
            submits.append(msg)
            job = {"job_id": f"job{n}", "request_id": msg.get("request_id")}
            ws.send(json.dumps({**job, "type": "accepted", "kind": msg["kind"], "state": "queued"}))
            result = {"source": "cube", "loss": 0.001,
                      "posterior": {"samples": 100, "modes": MODES if n else [], "intervals": {},
                                    "agreement": agreements[n], "sampler": {"runs": 2}}}
            if n:
                result["physics"] = PHYSICS
            ws.send(json.dumps({**job, "type": "result", "result": result}))
            ws.send(json.dumps({**job, "type": "done", "state": "done"}))

        ws.on_message(on_message)

    return handler


def test_a_posterior_whose_runs_disagree_gets_a_warning(page, web_server, artifacts):
    page.route_web_socket(re.compile(r".*/ws(\?.*)?$"), fake_server([
        {"max_rhat": 1.01, "limit": 1.1, "runs_agree": True},
        {"max_rhat": 1.42, "limit": 1.1, "runs_agree": False},
    ]))
    open_viewer(page, web_server)
    load_scene(page, "scenes/toss.xml")

    def run_and_wait(count):
        page.click("#run-solve")
        page.wait_for_function(f"window.dejaview.state().jobs.filter(j => j.state === 'done').length === {count}")
        return [n for n in state(page)["notifications"] if n["kind"] == "warning"]

    assert run_and_wait(1) == []  # the runs agree: no warning
    assert state(page)["agreement"].startswith("The sampler's 2 independent runs agree (R-hat at most 1.01")
    warnings = run_and_wait(2)
    assert len(warnings) == 1 and "disagree" in warnings[0]["text"] and "1.42" in warnings[0]["text"]
    assert page.locator("#notifications li.warning").count() == 1
    s = state(page)
    assert s["agreement"].startswith("The sampler's independent runs disagree (R-hat up to 1.42 > 1.1)")
    assert s["modes"] == ["1. 70 %: from (0.01, -0.02, 0.40) at 0.50 m/s",
                          "2. 30 %: from (0.01, -0.02, 0.40) at 0.50 m/s, 4.0 rad/s"]
    assert s["physics"] == ["friction: 0.420 (90 %: 0.300 … 0.550)"]
    page.eval_on_selector("#posterior-view", "e => e.scrollIntoView({block: 'end'})")
    page.screenshot(path=artifacts / "posterior-warning.png")
