"""Issue 60: a damaged store or results folder does not stop a server: it starts, moves what it
cannot read aside, says so once, and serves the rest."""

import logging

import pytest

from .test_rest import submit, wait_state


def two_done_jobs(client):
    jobs = [submit(client, kind="solve", scene_path="ball.xml", overrides={"iterations": 2}) for _ in range(2)]
    for job in jobs:
        assert wait_state(client, job)["state"] == "done"
    return jobs


@pytest.mark.parametrize("damage", ["truncated", "overwritten"])
def test_a_store_that_cannot_be_read_is_moved_aside_and_the_server_serves(make_client, tmp_path, caplog, damage):
    first = make_client()
    two_done_jobs(first)
    first.__exit__(None, None, None)
    store = tmp_path / "results" / "jobs.sqlite3"
    data = store.read_bytes()
    store.write_bytes(data[:len(data) // 3] if damage == "truncated" else b"edited by hand" * 100)
    with caplog.at_level(logging.WARNING, logger="dejaview.server"):
        second = make_client()
    said = [r.getMessage() for r in caplog.records if "could not be read" in r.getMessage()]
    assert len(said) == 1 and "moved aside to jobs.sqlite3.unreadable-" in said[0], said
    aside = [p.name for p in store.parent.glob("jobs.sqlite3.unreadable-*") if not p.name.endswith(("-wal", "-shm"))]
    assert len(aside) == 1 and said[0].count(aside[0]) == 1
    assert second.get("/health").json()["status"] == "ok"
    job = submit(second, kind="simulate", scene_path="ball.xml")
    assert wait_state(second, job)["state"] == "done"


def test_a_result_edited_by_hand_is_moved_aside_and_the_rest_is_served(make_client, tmp_path, caplog):
    first = make_client()
    broken, kept = two_done_jobs(first)
    csv_kept = first.get(f"/jobs/{kept}/trajectory.csv").text
    first.__exit__(None, None, None)
    jobs = tmp_path / "results" / "jobs"
    (jobs / broken / "result.json").write_text('{"loss": 0.1, truncated')
    with caplog.at_level(logging.WARNING, logger="dejaview.server"):
        second = make_client()
    said = [r.getMessage() for r in caplog.records if "could not be read" in r.getMessage()]
    assert said == [f"1 finished job(s) whose artefacts could not be read moved aside to "
                    f"{tmp_path / 'results' / 'unreadable'}: {broken}"]
    status = second.get(f"/jobs/{broken}").json()
    assert status["state"] == "failed" and status["error"]["code"] == "result_unreadable"
    assert "result.json: " in status["error"]["message"] and status["artefacts"] == {}
    assert (tmp_path / "results" / "unreadable" / broken / "result.json").is_file()
    assert second.get(f"/jobs/{kept}/trajectory.csv").text == csv_kept
    with second.websocket_connect("/ws") as ws:  # subscribing to either job answers, nothing breaks
        for job in (broken, kept):
            ws.send_json({"type": "subscribe", "job_id": job})
            while (message := ws.receive_json())["type"] != "done":
                pass
            assert message["state"] == ("failed" if job == broken else "done")
