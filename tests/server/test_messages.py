"""The typed messages: one discriminated union per direction, strict validation, compact encoding."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from dejaview.server.messages import (
    CLIENT_MESSAGE,
    SERVER_MESSAGE,
    AcceptedMessage,
    CancelMessage,
    DoneMessage,
    ErrorMessage,
    HeatmapMessage,
    JobRequest,
    PingMessage,
    PongMessage,
    ProgressMessage,
    ResultMessage,
    SubmitMessage,
    SubscribeMessage,
    TrajectoryMessage,
    encode,
    first_error_line,
)

JOB = "0123456789abcdef0123456789abcdef"


@pytest.mark.parametrize("data, cls", [
    ({"type": "submit", "kind": "solve", "scene_path": "a.xml", "overrides": {"iterations": 5}}, SubmitMessage),
    ({"type": "submit", "kind": "heatmap", "scene_xml": "<scene/>", "request_id": "r",
      "overrides": {"cells": [4, 3], "samples": 2, "sigma": 0.1}}, SubmitMessage),
    ({"type": "cancel", "job_id": JOB}, CancelMessage),
    ({"type": "subscribe", "job_id": JOB, "request_id": "x"}, SubscribeMessage),
    ({"type": "ping"}, PingMessage),
])
def test_client_union_picks_the_type(data, cls):
    assert type(CLIENT_MESSAGE.validate_python(data)) is cls


@pytest.mark.parametrize("data, fragment", [
    ({"type": "submit", "kind": "solve"}, "exactly one of scene_xml and scene_path"),
    ({"type": "submit", "kind": "solve", "scene_xml": "x", "scene_path": "y"}, "exactly one"),
    ({"type": "submit", "kind": "bake", "scene_path": "a"}, "kind"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "overrides": {"iterations": "5"}}, "valid integer"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "overrides": {"iterations": 5.0}}, "valid integer"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "overrides": {"iterations": True}}, "valid integer"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "overrides": {"iterations": 0}}, "greater than"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "overrides": {"lr": float("nan")}}, "finite"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "overrides": {"optimizer": "sgd"}}, "optimizer"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "overrides": {"colour": 1}}, "Extra inputs"),
    ({"type": "submit", "kind": "simulate", "scene_path": "a", "overrides": {"iterations": 3}},
     "does not apply to simulate jobs"),
    ({"type": "submit", "kind": "solve", "scene_path": "a", "extra": 1}, "Extra inputs"),
    ({"type": "cancel", "job_id": "../../etc"}, "pattern"),
    ({"type": "cancel"}, "job_id"),
    ({"type": "ping", "request_id": "r" * 201}, "at most 200"),
    ({"type": "launch"}, "does not match any of the expected tags"),
])
def test_client_messages_are_strict(data, fragment):
    with pytest.raises(ValidationError) as info:
        CLIENT_MESSAGE.validate_python(data)
    assert fragment in first_error_line(info.value)
    assert "\n" not in first_error_line(info.value)


def test_job_request_is_the_submit_without_type():
    req = JobRequest.model_validate({"kind": "simulate", "scene_path": "a.xml", "overrides": {"steps": 3}})
    assert req.overrides.given() == {"steps": 3}


SERVER_EXAMPLES = [
    AcceptedMessage(job_id=JOB, request_id="r", kind="solve", state="queued", queue_position=1),
    ProgressMessage(job_id=JOB, iteration=2, total=10, loss=0.5, best_loss=float("nan"), elapsed_s=0.1),
    TrajectoryMessage(job_id=JOB, csv="step,time\n", url="/jobs/x/trajectory.csv", bytes=10),
    HeatmapMessage(job_id=JOB, ppm="P3\n1 1\n255\n0 0 0\n", ppm_url="/u.ppm", png_url="/u.png",
                   grid={"min": [0, 0], "max": [1, 1], "cells": [1, 1], "probability": [[1.0]]}),
    ResultMessage(job_id=JOB, result={"loss": float("inf")}, url="/u.json"),
    ErrorMessage(code="queue_full", message="full"),
    DoneMessage(job_id=JOB, state="cancelled"),
    PongMessage(request_id="p"),
]


@pytest.mark.parametrize("message", SERVER_EXAMPLES, ids=lambda m: m.type)
def test_server_messages_encode_as_strict_json_and_round_trip(message):
    text = encode(message)
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in {text}"))
    assert next(iter(data)) == "type"  # type first: easy to dispatch on
    assert all(v is not None for k, v in data.items() if k not in ("result", "best_loss"))
    again = SERVER_MESSAGE.validate_python(data)
    assert type(again) is type(message)


def test_non_finite_numbers_become_null():
    data = json.loads(encode(SERVER_EXAMPLES[1]))
    assert data["best_loss"] is None and data["loss"] == 0.5
    assert json.loads(encode(SERVER_EXAMPLES[4]))["result"] == {"loss": None}
