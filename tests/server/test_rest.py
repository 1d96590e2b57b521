"""REST routes under TestClient: every route, its errors, records on disk across restarts."""

from __future__ import annotations

import importlib.util
import json
import sqlite3
import subprocess
import sys
import time

import pytest

from dejaview.backends import warp_available
from dejaview.sim.trajectory_csv import HEADER, read_trajectory_csv
from dejaview.server.runner import ARTEFACTS

from .conftest import FIXTURES

BALL_XML = (FIXTURES / "ball.xml").read_text()


def wait_state(client, job_id, states=("done", "failed", "cancelled"), timeout=60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = client.get(f"/jobs/{job_id}").json()
        if status["state"] in states:
            return status
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} still {status['state']} after {timeout} s")


def submit(client, **body):
    response = client.post("/jobs", json=body)
    assert response.status_code == 202, response.text
    return response.json()["job_id"]


def test_health(client):
    body = client.get("/health").json()
    assert body["status"] == "ok" and body["version"]
    assert body["workers"] == 2 and body["executor"] == "thread" and body["queued"] == 0


def test_docs_and_openapi_list_routes_and_message_schemas(client):
    assert client.get("/docs").status_code == 200
    schema = client.get("/openapi.json").json()
    assert {"/health", "/jobs", "/jobs/{job_id}", "/jobs/{job_id}/{artefact}"} <= set(schema["paths"])
    assert set(schema["paths"]["/jobs/{job_id}"]) == {"get", "delete"}
    components = schema["components"]["schemas"]
    assert {"ClientMessage", "ServerMessage", "JobRequest", "JobStatus", "ErrorBody"} <= set(components)
    tags = set(components["ClientMessage"]["discriminator"]["mapping"])
    assert tags == {"submit", "cancel", "subscribe", "ping", "live"}
    assert "live-result" in components["ServerMessage"]["discriminator"]["mapping"]


def test_simulate_job_by_path(client):
    job_id = submit(client, kind="simulate", scene_path="ball.xml")
    status = wait_state(client, job_id)
    assert status["state"] == "done", status
    assert status["summary"]["steps"] == 20 and status["summary"]["bodies"] == ["ball"]
    assert status["summary"]["backend"] == "spheres"
    assert status["progress"]["iteration"] == status["progress"]["total"] == 20
    assert status["scene"] == {"scene_path": "ball.xml"}
    assert set(status["artefacts"]) == {"trajectory.csv"}
    response = client.get(status["artefacts"]["trajectory.csv"])
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/csv")
    traj = read_trajectory_csv(response.text)
    assert response.text.splitlines()[0] == ",".join(HEADER)
    assert traj["ball"]["position"][-1][0] == pytest.approx(0.1, abs=1e-9)  # 0.5 m/s for 0.2 s


@pytest.mark.skipif(not warp_available(), reason="the warp backend needs warp-lang (the warp extra)")
def test_simulate_job_on_the_warp_backend(client):
    """The ``backend`` override runs a simulate job in Warp. Skipped only where warp-lang (the
    ``warp`` extra, which ``scripts/setup`` installs) cannot be imported."""
    job_id = submit(client, kind="simulate", scene_path="ball.xml", overrides={"backend": "warp"})
    status = wait_state(client, job_id, timeout=120.0)
    assert status["state"] == "done", status
    assert status["summary"]["backend"] == "warp" and status["summary"]["steps"] == 20
    assert status["progress"]["iteration"] == status["progress"]["total"] == 20
    traj = read_trajectory_csv(client.get(status["artefacts"]["trajectory.csv"]).text)
    assert traj["ball"]["position"][-1][0] == pytest.approx(0.1, abs=1e-3)  # 0.5 m/s for 0.2 s
    assert traj["ball"]["position"][-1][2] == pytest.approx(0.4 - 0.5 * 9.81 * 0.2 ** 2, abs=0.01)


def test_solve_job_from_xml_text_with_overrides(client):
    job_id = submit(client, kind="solve", scene_xml=BALL_XML,
                    overrides={"iterations": 2, "optimizer": "gd", "seed": 3, "screen": 3})
    status = wait_state(client, job_id)
    assert status["state"] == "done", status
    assert status["overrides"] == {"iterations": 2, "optimizer": "gd", "seed": 3, "screen": 3}
    assert status["scene"]["scene_xml"].endswith("bytes>")
    assert {"trajectory.csv", "result.json", "iterations.csv"} <= set(status["artefacts"])
    result = client.get(f"/jobs/{job_id}/result.json").json()
    assert result["optimizer"] == "gd" and len(result["iterations"]) == 2
    assert result["screened"] == 4
    assert status["summary"]["loss"] == pytest.approx(result["loss"])
    assert client.get(f"/jobs/{job_id}/iterations.csv").text.startswith("iteration,loss")


def test_solve_job_with_posterior_samples(client):
    """Issue 20: the override ``samples`` draws the posterior; posterior.csv is an artefact and the
    summary carries the modes and intervals; the progress went through search and sample."""
    job_id = submit(client, kind="solve", scene_path="ball.xml",
                    overrides={"optimizer": "auto", "iterations": 40, "samples": 64})
    status = wait_state(client, job_id, timeout=120)
    assert status["state"] == "done", status
    assert "posterior.csv" in status["artefacts"]
    rows = client.get(f"/jobs/{job_id}/posterior.csv").text.splitlines()
    assert rows[0] == "sample,weight,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz" and len(rows) == 65
    post = status["summary"]["posterior"]
    assert post["samples"] == 64 and set(post["intervals"]) == {"position.x", "position.y", "linear_velocity.x",
                                                                 "linear_velocity.y", "linear_velocity.z"}
    assert status["progress"]["phase"] == "sample" and status["progress"]["fraction"] == 1.0
    if importlib.util.find_spec("arviz") is not None:  # the analysis extra: posterior.nc for ArviZ as well
        nc = client.get(f"/jobs/{job_id}/posterior.nc")
        assert nc.status_code == 200 and nc.headers["content-type"] == "application/x-netcdf"
        assert nc.content[:4] == b"\x89HDF" and "posterior.nc" in status["artefacts"]


@pytest.mark.parametrize("overrides, status_code, code, fragment", [
    ({"samples": -1}, 422, "invalid_message", "samples"),
    ({"samples": 10**6}, 422, "invalid_message", "samples"),
])
def test_bad_sample_overrides_are_refused(client, overrides, status_code, code, fragment):
    response = client.post("/jobs", json={"kind": "solve", "scene_path": "ball.xml", "overrides": overrides})
    assert response.status_code == status_code and response.json()["code"] == code
    assert fragment in response.json()["message"]


def test_samples_with_a_local_optimiser_fail_the_job_with_one_line(client):
    job_id = submit(client, kind="solve", scene_path="ball.xml", overrides={"samples": 5})  # scene: adam
    status = wait_state(client, job_id)
    assert status["state"] == "failed" and "default search" in status["error"]["message"]
    assert "\n" not in status["error"]["message"]


def test_heatmap_job(client):
    job_id = submit(client, kind="heatmap", scene_path="ball.xml", overrides={"iterations": 1})
    status = wait_state(client, job_id, timeout=120)
    assert status["state"] == "done", status
    ppm = client.get(f"/jobs/{job_id}/heatmap.ppm")
    assert ppm.status_code == 200 and ppm.text.startswith("P3")
    png = client.get(f"/jobs/{job_id}/heatmap.png")
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    grid = client.get(f"/jobs/{job_id}/heatmap.json").json()
    assert grid["cells"] == [2, 2]
    assert sum(map(sum, grid["probability"])) == pytest.approx(1.0)


def test_a_start_area_that_cannot_hold_the_source_fails_the_job_and_the_server_goes_on(client, tmp_path):
    """Issue 56: solve and heatmap jobs of a start area inside a desk fail with
    ``infeasible_start_area`` and the one line naming the objects and the depth; nothing but the
    scene is left in the job's folder; the server answers and runs the next job."""
    xml = (FIXTURES.parent / "inference" / "box_in_desk.xml").read_text()
    for kind in ("solve", "heatmap"):
        job_id = submit(client, kind=kind, scene_xml=xml)
        status = wait_state(client, job_id)
        assert status["state"] == "failed", status
        assert status["error"]["code"] == "infeasible_start_area"
        message = status["error"]["message"]
        assert "<start-area> (-0.2, -0.1, 0.7233) to (0.2, 0.1, 0.7233) cannot hold 'src': everywhere in it " \
               "'src' and 'desk' interpenetrate, by 0.0267 m" in message and "\n" not in message
        assert status["artefacts"] == {}
        assert client.get(f"/jobs/{job_id}/result.json").json()["code"] == "no_artefact"
        assert sorted(p.name for p in (tmp_path / "results" / "jobs" / job_id).iterdir()) == ["scene.xml"]
    assert client.get("/health").json()["status"] == "ok"
    assert wait_state(client, submit(client, kind="solve", scene_path="ball.xml"))["state"] == "done"


def test_cancel_running_job_stops_within_an_iteration(make_client):
    client = make_client(workers=1)
    job_id = submit(client, kind="solve", scene_path="solve_endless.xml")
    status = wait_state(client, job_id, states=("running",))
    deadline = time.monotonic() + 60
    while status["progress"] is None and time.monotonic() < deadline:
        status = client.get(f"/jobs/{job_id}").json()
    response = client.delete(f"/jobs/{job_id}")
    assert response.status_code == 202
    at_cancel = response.json()["progress"]["iteration"]
    status = wait_state(client, job_id)
    assert status["state"] == "cancelled"
    assert status["progress"]["iteration"] <= at_cancel + 2  # the one running plus a report in flight
    # finished: cannot cancel again, and it has no artefacts
    assert client.delete(f"/jobs/{job_id}").json()["code"] == "not_cancellable"
    assert client.get(f"/jobs/{job_id}/trajectory.csv").status_code == 404


def test_a_job_over_the_time_limit_fails_with_timeout(make_client):
    client = make_client(workers=1, job_timeout_s=0.5)
    job_id = submit(client, kind="solve", scene_path="solve_endless.xml")
    status = wait_state(client, job_id)
    assert status["state"] == "failed" and status["error"]["code"] == "timeout", status
    assert status["progress"] is None or status["progress"]["iteration"] < 10_000


def test_queued_job_is_cancelled_at_once_and_queue_positions(make_client):
    client = make_client(workers=1)
    first = submit(client, kind="solve", scene_path="solve_endless.xml")
    second = submit(client, kind="simulate", scene_path="ball.xml")
    third = submit(client, kind="simulate", scene_path="drop.xml")
    assert client.get(f"/jobs/{second}").json()["queue_position"] == 1
    assert client.get(f"/jobs/{third}").json()["queue_position"] == 2
    assert client.get("/health").json()["queued"] == 2
    cancelled = client.delete(f"/jobs/{second}")
    assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
    assert client.get(f"/jobs/{third}").json()["queue_position"] == 1
    client.delete(f"/jobs/{first}")
    assert wait_state(client, third)["state"] == "done"


def test_full_queue_answers_503(make_client):
    client = make_client(workers=1, queue_size=1)
    submit(client, kind="solve", scene_path="solve_endless.xml")  # runs
    submit(client, kind="simulate", scene_path="ball.xml")     # waits
    response = client.post("/jobs", json={"kind": "simulate", "scene_path": "ball.xml"})
    assert response.status_code == 503
    assert response.json()["code"] == "queue_full" and "try again" in response.json()["message"]


@pytest.mark.parametrize("body, status, code", [
    ({"kind": "solve"}, 422, "invalid_message"),
    ({"kind": "solve", "scene_path": "ball.xml", "scene_xml": BALL_XML}, 422, "invalid_message"),
    ({"kind": "teleport", "scene_path": "ball.xml"}, 422, "invalid_message"),
    ({"kind": "solve", "scene_path": 7}, 422, "invalid_message"),
    ({"kind": "solve", "scene_path": "ball.xml", "overrides": {"iterations": -1}}, 422, "invalid_message"),
    ({"kind": "solve", "scene_path": "ball.xml", "overrides": {"bogus": 1}}, 422, "invalid_message"),
    ({"kind": "solve", "scene_path": "ball.xml", "overrides": {"screen": -1}}, 422, "invalid_message"),
    ({"kind": "solve", "scene_path": "ball.xml", "overrides": {"iterations": 100000}}, 422, "limit_exceeded"),
    ({"kind": "solve", "scene_path": "drop.xml"}, 422, "invalid_scene"),
    ({"kind": "solve", "scene_xml": "<scene"}, 422, "invalid_scene"),
    ({"kind": "solve", "scene_path": "../outside/secret.xml"}, 400, "path_outside_root"),
    ({"kind": "solve", "scene_path": "/etc/passwd"}, 400, "path_outside_root"),
    ({"kind": "solve", "scene_path": "escape.xml"}, 400, "path_outside_root"),
    ({"kind": "solve", "scene_path": "nope.xml"}, 400, "scene_not_found"),
    ({"kind": "simulate", "scene_xml": "<a/>" * 300_000}, 413, "scene_too_large"),
])
def test_bad_job_requests(client, body, status, code):
    response = client.post("/jobs", json=body)
    assert response.status_code == status, response.text
    error = response.json()
    assert error["code"] == code and error["message"] and "\n" not in error["message"]


def test_bad_bodies(client):
    assert client.post("/jobs", content=b"{not json", headers={"content-type": "application/json"}
                       ).json()["code"] == "invalid_json"
    assert client.post("/jobs", content=b'{"kind": NaN}', headers={"content-type": "application/json"}
                       ).status_code in (400, 422)
    assert client.post("/jobs", content=b"[1, 2]", headers={"content-type": "application/json"}
                       ).status_code == 422
    big = client.post("/jobs", content=b" " * (3 << 20), headers={"content-type": "application/json"})
    assert big.status_code == 413 and big.json()["code"] == "message_too_large"

    def chunks():  # no Content-Length: counted as it streams
        for _ in range(40):
            yield b" " * 100_000
    assert client.post("/jobs", content=chunks(), headers={"content-type": "application/json"}
                       ).status_code == 413


def test_body_limit_is_configurable(make_client):
    client = make_client(max_body_bytes=1000)
    response = client.post("/jobs", json={"kind": "simulate", "scene_xml": BALL_XML})
    assert response.status_code == 413 and "1000 bytes" in response.json()["message"]


def test_unknown_jobs_routes_and_artefacts(client):
    missing = "0" * 32
    assert client.get(f"/jobs/{missing}").json()["code"] == "not_found"
    assert client.get("/jobs/..%2F..%2Fetc").status_code == 404
    assert client.delete(f"/jobs/{missing}").status_code == 404
    assert client.get(f"/jobs/{missing}/trajectory.csv").status_code == 404
    assert client.get("/no/such/route").json() == {"code": "not_found", "message": "Not Found"}
    assert client.put("/jobs").status_code == 405
    job_id = submit(client, kind="simulate", scene_path="ball.xml")
    assert client.get(f"/jobs/{job_id}/scene.xml").status_code == 422  # not an artefact name
    assert client.get(f"/jobs/{job_id}/job.json").status_code == 422
    wait_state(client, job_id)
    response = client.get(f"/jobs/{job_id}/result.json")
    assert response.status_code == 404 and response.json()["code"] == "no_artefact"


def test_artefact_before_done_is_not_ready(make_client):
    client = make_client(workers=1)
    job_id = submit(client, kind="solve", scene_path="solve_endless.xml")
    response = client.get(f"/jobs/{job_id}/trajectory.csv")
    assert response.status_code == 409 and response.json()["code"] == "not_ready"
    client.delete(f"/jobs/{job_id}")


def test_records_survive_a_restart(make_client, tmp_path):
    first = make_client()
    done = submit(first, kind="simulate", scene_path="ball.xml")
    wait_state(first, done)
    csv_before = first.get(f"/jobs/{done}/trajectory.csv").text
    first.__exit__(None, None, None)
    results = tmp_path / "results"
    with sqlite3.connect(results / "jobs.sqlite3") as db:
        assert db.execute("PRAGMA journal_mode").fetchone() == ("wal",)
        assert db.execute("SELECT state FROM jobs WHERE job_id = ?", (done,)).fetchone() == ("done",)
    # records of an older version (job.json files): finished ones are imported as they are, unfinished
    # ones (no job spec to run them with) fail, a broken one is skipped
    jobs = results / "jobs"
    for job_id, state in (("a" * 32, "queued"), ("b" * 32, "running"), ("d" * 32, "done")):
        (jobs / job_id).mkdir()
        (jobs / job_id / "job.json").write_text(json.dumps(
            {"job_id": job_id, "kind": "solve", "state": state, "created_at": 1.0}))
    (jobs / ("c" * 32)).mkdir()
    (jobs / ("c" * 32) / "job.json").write_text("{broken")

    second = make_client()
    status = second.get(f"/jobs/{done}").json()
    assert status["state"] == "done"
    assert second.get(f"/jobs/{done}/trajectory.csv").text == csv_before
    for job_id in ("a" * 32, "b" * 32):
        status = second.get(f"/jobs/{job_id}").json()
        assert status["state"] == "failed" and status["error"]["code"] == "interrupted"
    assert second.get(f"/jobs/{'d' * 32}").json()["state"] == "done"
    assert second.get(f"/jobs/{'c' * 32}").status_code == 404


def test_a_stopped_server_runs_its_unfinished_jobs_after_a_restart(make_client, tmp_path):
    first = make_client(workers=1)
    running = submit(first, kind="solve", scene_path="solve_long.xml", overrides={"iterations": 10_000})
    queued = submit(first, kind="simulate", scene_path="ball.xml")
    wait_state(first, running, states=("running",))
    first.__exit__(None, None, None)
    second = make_client(workers=2)
    assert second.get(f"/jobs/{running}").json()["state"] in ("queued", "running")
    status = wait_state(second, queued)
    assert status["state"] == "done" and status["error"] is None
    fresh = submit(second, kind="simulate", scene_path="ball.xml")
    wait_state(second, fresh)
    assert (second.get(f"/jobs/{queued}/trajectory.csv").text
            == second.get(f"/jobs/{fresh}/trajectory.csv").text)
    wait_state(second, running, states=("running",))  # run again, from the start
    assert second.delete(f"/jobs/{running}").status_code == 202
    assert wait_state(second, running)["state"] == "cancelled"
    leftovers = [p.name for p in (tmp_path / "results" / "jobs").glob("*/.*")]
    assert leftovers == []  # no half-written artefact or temporary file is left behind


def test_one_server_per_results_dir(tmp_path, scene_root):
    from dejaview.server.store import JobStore

    store = JobStore(tmp_path / "results")  # this process holds the results dir: another cannot
    try:
        code = ("import sys; from dejaview.server.store import JobStore\n"
                "try:\n    JobStore(sys.argv[1])\nexcept Exception as exc:\n    print(exc.code, exc.message)")
        out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "results")], capture_output=True,
                             text=True, timeout=60)
        assert out.stdout.startswith("results_dir_busy") and "another dejaview server" in out.stdout, out
    finally:
        store.close()


def test_old_jobs_are_pruned(make_client, tmp_path):
    client = make_client(keep_jobs=2)
    ids = []
    for _ in range(3):
        ids.append(submit(client, kind="simulate", scene_path="drop.xml"))
        wait_state(client, ids[-1])
    assert client.get(f"/jobs/{ids[0]}").status_code == 404
    assert not (tmp_path / "results" / "jobs" / ids[0]).exists()
    assert all(client.get(f"/jobs/{i}").status_code == 200 for i in ids[1:])


def test_artefact_media_types():
    assert ARTEFACTS["heatmap.ppm"] == "image/x-portable-pixmap" and ARTEFACTS["heatmap.png"] == "image/png"
