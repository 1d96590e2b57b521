"""Issue 60 in the service: a job sized over its memory limit fails before any work, a full disk
fails the job with ``disk_full`` and no half-written artefact, and the server goes on serving."""

import pytest

from .conftest import FIXTURES
from .test_rest import submit, wait_state

BALL_XML = (FIXTURES / "ball.xml").read_text()


def test_a_full_disk_fails_the_job_leaves_no_half_set_and_the_server_goes_on(make_client, tmp_path,
                                                                                 disk_full_at):
    client = make_client()
    earlier = submit(client, kind="solve", scene_path="ball.xml", overrides={"iterations": 2})
    assert wait_state(client, earlier)["state"] == "done"
    earlier_result = client.get(f"/jobs/{earlier}/result.json").json()
    disk_full_at("trajectory.csv")  # result.json and iterations.csv are written first
    job = submit(client, kind="solve", scene_path="ball.xml", overrides={"iterations": 2})
    status = wait_state(client, job)
    assert status["state"] == "failed" and status["error"]["code"] == "disk_full", status
    message = status["error"]["message"]
    folder = tmp_path / "results" / "jobs" / job
    assert message.startswith(f"cannot write {folder / 'trajectory.csv'}: No space left on device (the disk is "
                              f"full); the result set was not written") and "\n" not in message
    assert status["artefacts"] == {}
    assert sorted(p.name for p in folder.iterdir()) == ["scene.xml"]  # nothing half written
    assert [p.name for p in folder.parent.iterdir() if p.name.startswith(".")] == []
    assert client.get("/health").json()["status"] == "ok"
    assert client.get(f"/jobs/{earlier}/result.json").json() == earlier_result
    disk_full_at(None)  # the disk is freed: the next job runs as before
    again = submit(client, kind="solve", scene_path="ball.xml", overrides={"iterations": 2})
    assert wait_state(client, again)["state"] == "done"
    assert client.get(f"/jobs/{again}/result.json").json()["loss"] == earlier_result["loss"]


def test_a_job_sized_over_the_memory_limit_fails_before_any_work(make_client, tmp_path):
    client = make_client(max_job_memory_bytes=2 ** 30)
    job = submit(client, kind="solve", scene_xml=BALL_XML, overrides={"optimizer": "auto", "samples": 100_000})
    status = wait_state(client, job)
    assert status["state"] == "failed" and status["error"]["code"] == "limit_exceeded", status
    message = status["error"]["message"]
    assert message.startswith("100000 posterior samples would need about ") and "\n" not in message
    assert message.endswith("over the limit of 1 GiB (this server's limit for one job)")
    assert status["progress"] is None  # refused before the search's first iteration
    assert sorted(p.name for p in (tmp_path / "results" / "jobs" / job).iterdir()) == ["scene.xml"]


TINY_TRAIN = {"simulations": 400, "epochs": 5, "patience": 5, "transforms": 2, "hidden": [32, 32], "batch": 128}


def test_a_train_job_sized_over_the_memory_limit_fails_before_any_simulation(make_client, tmp_path):
    """A train job is sized (its training set, a batch of rollouts, the flow's fit) like the other
    kinds: 64 MiB cannot hold it, refused before the first simulation with the same one line; 8 GiB
    can, and it trains."""
    pytest.importorskip("zuko", reason="the amortised extra (pip install 'dejaview[amortised]')")
    client = make_client(max_job_memory_bytes=64 * 2 ** 20)
    job = submit(client, kind="train", scene_path="throw.xml", overrides=TINY_TRAIN)
    status = wait_state(client, job)
    assert status["state"] == "failed" and status["error"]["code"] == "limit_exceeded", status
    message = status["error"]["message"]
    assert message.startswith("400 training simulations would need about ") and "\n" not in message
    assert message.endswith("over the limit of 64 MiB (this server's limit for one job)")
    assert status["progress"] is None  # refused before the first chunk was simulated
    assert sorted(p.name for p in (tmp_path / "results" / "jobs" / job).iterdir()) == ["scene.xml"]
    models = tmp_path / "results" / "models"
    assert not models.exists() or not list(models.iterdir())


def test_a_train_job_within_the_memory_limit_trains(make_client):
    pytest.importorskip("zuko", reason="the amortised extra (pip install 'dejaview[amortised]')")
    client = make_client(max_job_memory_bytes=8 * 2 ** 30)
    job = submit(client, kind="train", scene_path="throw.xml", overrides=TINY_TRAIN)
    status = wait_state(client, job)
    assert status["state"] == "done" and status["summary"]["simulations"] == 400, status
