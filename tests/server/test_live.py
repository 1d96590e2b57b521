"""End to end: a real ``dejaview serve`` process (process workers) driven by the ``websockets``
client library through ``dejaview.server.client``."""

from __future__ import annotations

import asyncio
import json
import time

import pytest

from dejaview.sim.trajectory_csv import HEADER, read_trajectory_csv
from dejaview.server.client import get_json, http_get, run_job, submit_job, wait_healthy
from dejaview.server.local import LocalServer


def wait_state(base: str, job_id: str, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = get_json(f"{base}/jobs/{job_id}")
        if status["state"] in ("done", "failed", "cancelled"):
            return status
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} not finished after {timeout} s: {status}")


def test_solve_streams_progress_and_a_trajectory(live_server, tmp_path):
    outcome = run_job(live_server.ws_url, "solve", scene_path="ball.xml", out_dir=tmp_path, timeout=120)
    assert outcome.state == "done", outcome.messages[-2:]
    kinds = [m["type"] for m in outcome.messages]
    assert kinds[0] == "accepted" and "progress" in kinds and kinds[-3:] == ["trajectory", "result", "done"]
    last = outcome.of_type("progress")[-1]
    assert last["iteration"] == last["total"] == 3 and last["best_loss"] > 0
    assert set(outcome.files) == {"trajectory.csv", "result.json"}
    assert (tmp_path / "trajectory.csv").read_text().splitlines()[0] == ",".join(HEADER)
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["loss"] == pytest.approx(outcome.result["loss"]) and len(result["iterations"]) == 3
    # the trajectory starts where the result says the ball started
    start = read_trajectory_csv(outcome.csv)["ball"]["position"][0]
    assert start == pytest.approx(result["initial_state"]["position"], abs=1e-8)


def test_two_clients_run_at_the_same_time(live_server):
    async def both():
        return await asyncio.gather(
            submit_job(live_server.ws_url, "solve", scene_path="ball.xml", overrides={"iterations": 6},
                       timeout=120),
            submit_job(live_server.ws_url, "solve", scene_path="throw.xml", overrides={"iterations": 6},
                       timeout=120))

    a, b = asyncio.run(both())
    assert a.state == b.state == "done"
    sa, sb = (get_json(f"{live_server.http_url}/jobs/{o.job_id}") for o in (a, b))
    # two workers: each started before the other finished
    assert sa["started_at"] < sb["finished_at"] and sb["started_at"] < sa["finished_at"]


def test_heatmap_job_runs_beside_a_solve(live_server, tmp_path):
    async def both():
        return await asyncio.gather(
            submit_job(live_server.ws_url, "solve", scene_path="ball.xml", overrides={"iterations": 6},
                       timeout=300),
            submit_job(live_server.ws_url, "heatmap", scene_path="ball.xml", out_dir=tmp_path,
                       overrides={"iterations": 2}, timeout=300))

    solve, heat = asyncio.run(both())
    assert solve.state == "done" and heat.state == "done", heat.messages[-2:]
    assert {"heatmap.ppm", "heatmap.png", "heatmap.json", "trajectory.csv", "result.json"} <= set(heat.files)
    assert (tmp_path / "heatmap.ppm").read_text().startswith("P3")
    assert (tmp_path / "heatmap.png").read_bytes()[:4] == b"\x89PNG"
    s1, s2 = (get_json(f"{live_server.http_url}/jobs/{o.job_id}") for o in (solve, heat))
    assert s1["started_at"] < s2["finished_at"] and s2["started_at"] < s1["finished_at"]


def test_a_client_that_disconnects_fetches_the_result_over_rest(live_server):
    async def submit_and_leave():
        from websockets.asyncio.client import connect

        async with connect(live_server.ws_url) as ws:
            await ws.send(json.dumps({"type": "submit", "kind": "solve", "scene_path": "solve_long.xml",
                                      "overrides": {"iterations": 8}}))
            accepted = json.loads(await ws.recv())
            while json.loads(await ws.recv())["type"] != "progress":
                pass
            return accepted["job_id"]  # leaves mid-job

    job_id = asyncio.run(submit_and_leave())
    status = wait_state(live_server.http_url, job_id)
    assert status["state"] == "done" and status["progress"]["iteration"] == 8
    csv_text = http_get(status["artefacts"]["trajectory.csv"]).decode()
    assert read_trajectory_csv(csv_text)["ball"]["step"][-1] == 20
    result = get_json(status["artefacts"]["result.json"])
    assert len(result["iterations"]) == 8


def test_cancel_stops_a_running_solve(live_server):
    outcome = run_job(live_server.ws_url, "solve", scene_path="solve_endless.xml", timeout=120,
                      cancel_when=lambda m: m["type"] == "progress")
    assert outcome.state == "cancelled"
    progress = outcome.of_type("progress")
    assert progress[-1]["iteration"] <= progress[0]["iteration"] + 2
    status = get_json(f"{live_server.http_url}/jobs/{outcome.job_id}")
    assert status["state"] == "cancelled" and status["progress"]["iteration"] < 500


def test_bare_text_mode_against_the_real_server(live_server):
    async def bare():
        from websockets.asyncio.client import connect

        async with connect(live_server.ws_url) as ws:
            await ws.send("drop.xml")
            csv_text = await asyncio.wait_for(ws.recv(), 60)
            await ws.send("../outside/secret.xml")
            error = await asyncio.wait_for(ws.recv(), 60)
            return csv_text, error

    csv_text, error = asyncio.run(bare())
    assert csv_text.startswith(",".join(HEADER)) and error.startswith("error: ")


def test_server_is_healthy_after_all_of_it(live_server):
    health = wait_healthy(live_server.http_url, timeout=10)
    assert health["workers_ready"] == health["workers"] == 2
    assert live_server.process.poll() is None
    outcome = run_job(live_server.ws_url, "simulate", scene_path="drop.xml", timeout=60)
    assert outcome.state == "done"


def test_a_killed_server_restarts_with_its_records(tmp_path, live_root):
    results = tmp_path / "results"
    with LocalServer(live_root, results, log_path=tmp_path / "a.log", workers=1) as server:
        done = run_job(server.ws_url, "simulate", scene_path="ball.xml", timeout=120)
        assert done.state == "done"

        async def start_long():
            from websockets.asyncio.client import connect

            async with connect(server.ws_url) as ws:
                await ws.send(json.dumps({"type": "submit", "kind": "solve", "scene_path": "solve_long.xml"}))
                job_id = json.loads(await ws.recv())["job_id"]
                while json.loads(await ws.recv())["type"] != "progress":
                    pass
                return job_id
        running = asyncio.run(start_long())
        server.stop(kill=True)  # SIGKILL: no chance to write anything
    with LocalServer(live_root, results, log_path=tmp_path / "b.log", workers=1) as server:
        status = get_json(f"{server.http_url}/jobs/{done.job_id}")
        assert status["state"] == "done"
        assert http_get(f"{server.http_url}/jobs/{done.job_id}/trajectory.csv").decode() == done.csv
        # the job cut off by the crash runs again, to the end (tests/server/test_durable.py: more)
        status = wait_state(server.http_url, running, timeout=300)
        assert status["state"] == "done" and status["error"] is None, status
