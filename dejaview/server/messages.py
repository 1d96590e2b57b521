"""Typed messages of the service protocol (``shared/spec/protocol.md``, version 1).

Client to server (``ClientMessage``, discriminated by ``type``): ``submit``,
``cancel``, ``ping``, ``live`` (the addition "Live answers": one observation answered from the
scene's amortised model, ``dejaview.server.live``) and ``subscribe`` (an extension: follow a job
submitted elsewhere, e.g. after a reconnect). Server to client (``ServerMessage``):
``accepted``, ``progress``, ``trajectory``, ``heatmap``, ``result``,
``error``, ``done``, ``pong``, ``live-result``. REST bodies reuse the same models
(``JobRequest``, ``JobStatus``, ``ErrorBody``).

Validation is strict: unknown keys are refused everywhere, numbers must be
JSON numbers (``"100"`` is not an integer), NaN and infinities are refused,
and each override is checked against the job kind it applies to.

Error codes (``error.code`` on the WebSocket, ``code`` of a REST error body,
with the HTTP status REST answers with):

===================== ====== ===================================================
code                  status meaning
===================== ====== ===================================================
unauthorized          401    missing or wrong token (WebSocket: closed with code 4401)
forbidden_origin      403    a browser page of another origin (WebSocket: handshake refused)
forbidden_host        403    a ``Host`` that is not a name of a loopback-only server
invalid_json          400    the text is not JSON (or holds NaN / Infinity)
invalid_message       422    JSON that is not a valid message / request
unknown_type          422    a message ``type`` the server does not know
binary_frame          --     a binary WebSocket frame (only text is spoken)
message_too_large     413    a WebSocket message or request body over its limit
rate_limited          --     more messages per second than the connection may send
scene_too_large       413    scene XML over the scene size limit
invalid_scene         422    the scene XML is malformed or invalid (file:line: <element> reason)
scene_not_found       400    ``scene_path`` names no file inside the scene root
path_outside_root     400    a scene or mesh path that leaves the scene root
limit_exceeded        422    a job bigger than the server allows (steps, iterations, heatmap size);
                             as a failed job's error, before any work: its memory estimate is over
                             the server's limit for one job (posterior samples, heatmap cells,
                             simulation records: the one line names the estimate and the limit)
queue_full            503    the job queue is full: retry later
store_error           503    the job store (SQLite in the results dir) cannot be written
disk_full             507    the results dir's disk is full: a job is refused (REST) or fails with
                             nothing of its result set written (the path named); retry later
write_failed          500    a job's files could not be written for another reason (permission...)
too_many_jobs         429    this connection has too many unfinished jobs
not_found             404    no such job (or route)
not_ready             409    the job has not finished: no artefacts yet
no_artefact           404    the job finished without this artefact
not_cancellable       409    the job has already finished
no_model              --     a ``live`` message for a scene that has no amortised model in the server's
                             models folder (``<results_dir>/models``): submit a ``train`` job first
simulation_error      --     the job failed in the simulator
geometry_error        --     the job failed loading a mesh or packing
inference_error       --     the job failed in the optimiser
infeasible_start_area --     the start area cannot hold the source (inside other objects
                             everywhere, or beyond the bounds of positions): the one line names
                             the objects and the depth; checked before any work
timeout               --     the job ran longer than the server's job time limit
interrupted           --     the server stopped under the job 5 times (or its record is from an
                             older version); a job is otherwise run again after a restart
worker_crashed        --     the job's worker process died twice while running it
result_unreadable     --     a finished job whose artefacts could not be read when the server
                             started (moved aside to ``<results_dir>/unreadable/<id>``)
internal_error        500    a bug: the message names the exception
===================== ====== ===================================================

"--" codes appear only as a failed job's ``error`` (and on the WebSocket).
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from dejaview.scene.model import OPTIMIZERS

JobKind = Literal["simulate", "solve", "heatmap", "train"]
JobState = Literal["queued", "running", "done", "failed", "cancelled"]
FINISHED_STATES = ("done", "failed", "cancelled")

RequestId = Annotated[str, Field(max_length=200, description="echoed in every reply about this request")]
JobId = Annotated[str, Field(pattern=r"^[0-9a-f]{32}$", description="32 hex digits")]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class Overrides(_Strict):
    """Settings that override the scene's for one job (all optional).

    simulate: ``steps``, ``record_every``; solve: ``iterations``,
    ``optimizer``, ``budget`` (the default search's), ``seed``, ``tolerance``, ``samples``
    (posterior samples: posterior.csv), and the local
    optimisers' ``gradient``, ``lr``, ``multistart``, ``screen``, ``screen_rounds``; heatmap: ``iterations``, ``optimizer``, ``gradient``,
    ``seed``, ``cells``, ``samples`` (per cell), ``sigma``; ``backend`` to all three; train
    (``TrainParams``): ``simulations``, ``seed``, ``epochs``, ``patience``, ``transforms``,
    ``hidden``, ``batch``, ``lr``.
    """

    backend: Literal["spheres", "warp"] | None = None
    iterations: Annotated[int, Field(ge=1)] | None = None
    optimizer: Literal[OPTIMIZERS] | None = None
    budget: Annotated[int, Field(ge=1, le=10**7)] | None = None
    gradient: Literal["forward", "reverse"] | None = None
    seed: Annotated[int, Field(ge=0, lt=2**63)] | None = None
    lr: Annotated[float, Field(gt=0)] | None = None
    multistart: Annotated[int, Field(ge=1, le=64)] | None = None
    screen: Annotated[int, Field(ge=0, le=1024)] | None = None
    screen_rounds: Annotated[int, Field(ge=1, le=16)] | None = None
    tolerance: Annotated[float, Field(ge=0)] | None = None
    steps: Annotated[int, Field(ge=1)] | None = None
    record_every: Annotated[int, Field(ge=1)] | None = None
    cells: Annotated[list[Annotated[int, Field(ge=1)]],
                     Field(min_length=2, max_length=2, description="[nx, ny]")] | None = None
    samples: Annotated[int, Field(ge=0, le=100_000)] | None = None
    sigma: Annotated[float, Field(gt=0)] | None = None
    simulations: Annotated[int, Field(ge=2)] | None = None
    epochs: Annotated[int, Field(ge=1, le=10_000)] | None = None
    patience: Annotated[int, Field(ge=1, le=10_000)] | None = None
    transforms: Annotated[int, Field(ge=1, le=16)] | None = None
    hidden: Annotated[list[Annotated[int, Field(ge=1, le=1024)]],
                      Field(min_length=1, max_length=6, description="hidden layer widths")] | None = None
    batch: Annotated[int, Field(ge=1, le=65_536)] | None = None

    def given(self) -> dict[str, Any]:
        """The overrides actually set."""
        return self.model_dump(exclude_none=True)


OVERRIDES_BY_KIND: dict[str, frozenset[str]] = {
    "simulate": frozenset({"backend", "steps", "record_every"}),
    "solve": frozenset({"backend", "iterations", "optimizer", "budget", "gradient", "seed", "lr",
                        "multistart", "screen", "screen_rounds", "tolerance", "samples"}),
    "heatmap": frozenset({"backend", "iterations", "optimizer", "gradient", "seed", "cells", "samples",
                          "sigma"}),
    "train": frozenset({"simulations", "seed", "epochs", "patience", "transforms", "hidden", "batch", "lr"}),
}


class JobRequest(_Strict):
    """A job: its kind, the scene (XML text or a path inside the scene root) and overrides."""

    kind: JobKind
    scene_xml: str | None = Field(None, description="the scene as XML text; relative mesh paths "
                                                    "resolve against the scene root")
    scene_path: str | None = Field(None, description="a scene file, relative to the scene root")
    overrides: Overrides | None = None

    @model_validator(mode="after")
    def _one_scene_and_matching_overrides(self):
        if (self.scene_xml is None) == (self.scene_path is None):
            raise ValueError("give exactly one of scene_xml and scene_path")
        if self.overrides is not None:
            stray = sorted(set(self.overrides.given()) - OVERRIDES_BY_KIND[self.kind])
            if stray:
                raise ValueError(f"override {', '.join(stray)} does not apply to {self.kind} jobs "
                                 f"(allowed: {', '.join(sorted(OVERRIDES_BY_KIND[self.kind]))})")
        return self


# ---------------------------------------------------------------- client -> server
class SubmitMessage(JobRequest):
    type: Literal["submit"]
    request_id: RequestId | None = None


class CancelMessage(_Strict):
    type: Literal["cancel"]
    job_id: JobId
    request_id: RequestId | None = None


class SubscribeMessage(_Strict):
    """Extension: receive a job's remaining messages (all of them again if it has finished)."""

    type: Literal["subscribe"]
    job_id: JobId
    request_id: RequestId | None = None


class PingMessage(_Strict):
    type: Literal["ping"]
    request_id: RequestId | None = None


class LiveTarget(_Strict):
    """Where the source is seen now: it replaces the scene's (last) ``<target>`` in the observation."""

    position: Annotated[list[Annotated[float, Field(ge=-1e4, le=1e4)]],
                        Field(min_length=3, max_length=3, description="[x, y, z] metres")]
    orientation: Annotated[list[Annotated[float, Field(ge=-1e4, le=1e4)]],
                           Field(min_length=4, max_length=4, description="[w, x, y, z]; ignored where the "
                                 "scene's target gives no orientation")] | None = None

    @model_validator(mode="after")
    def _unit_quaternion(self):
        if self.orientation is not None and sum(v * v for v in self.orientation) < 1e-12:
            raise ValueError("target.orientation is a zero quaternion: give [w, x, y, z] of a rotation")
        return self


class LiveMessage(_Strict):
    """The addition "Live answers": the answer to one observation of a scene with an amortised model,
    ``live-result`` within milliseconds; the newest of a connection's waiting ``live`` messages is
    answered and the others dropped."""

    type: Literal["live"]
    scene_xml: str | None = None
    scene_path: str | None = None
    target: LiveTarget
    cells: Annotated[list[Annotated[int, Field(ge=1, le=64)]],
                     Field(min_length=2, max_length=2, description="[nx, ny] of the heatmap (default 16 x 16)")] | None = None
    request_id: RequestId | None = None

    @model_validator(mode="after")
    def _one_scene(self):
        if (self.scene_xml is None) == (self.scene_path is None):
            raise ValueError("give exactly one of scene_xml and scene_path")
        return self


ClientMessage = Annotated[Union[SubmitMessage, CancelMessage, SubscribeMessage, PingMessage, LiveMessage],
                          Field(discriminator="type")]
CLIENT_MESSAGE = TypeAdapter(ClientMessage)


# ---------------------------------------------------------------- server -> client
class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _JobMessage(_Out):
    job_id: str
    request_id: str | None = None


class AcceptedMessage(_JobMessage):
    type: Literal["accepted"] = "accepted"
    kind: JobKind
    state: JobState
    queue_position: int | None = Field(None, description="1 = next to run; None once running")


class ProgressData(BaseModel):
    """Where a running job is. ``iteration`` counts optimiser iterations (solve, heatmap) or
    steps (simulate); ``total`` is their number; losses are absent for simulate jobs. ``phase``
    says which stage of a solve or heatmap runs (``search``, ``refine``, ``sample``; the basins
    heatmap's ``optimize``, ``robustness``) and ``fraction`` how far the sampler is (0 to 1)."""

    model_config = ConfigDict(extra="forbid")

    iteration: int
    total: int | None = None
    loss: float | None = None
    best_loss: float | None = None
    elapsed_s: float
    evaluations: int | None = None
    cells_done: int | None = None
    cells_total: int | None = None
    phase: str | None = None
    fraction: float | None = None


class ProgressMessage(_JobMessage, ProgressData):
    type: Literal["progress"] = "progress"


class TrajectoryMessage(_JobMessage):
    type: Literal["trajectory"] = "trajectory"
    csv: str | None = Field(None, description="inline unless larger than the inline limit")
    url: str
    bytes: int


class HeatmapMessage(_JobMessage):
    type: Literal["heatmap"] = "heatmap"
    ppm: str | None = Field(None, description="PPM P3 inline unless larger than the inline limit")
    ppm_url: str
    png_url: str | None = None
    grid: dict | None = Field(None, description="heatmap.json: min, max, cells, probability[j][i]")
    grid_url: str | None = None


class ResultMessage(_JobMessage):
    type: Literal["result"] = "result"
    result: dict | None = Field(None, description="result.json inline unless larger than the inline limit")
    url: str


class ErrorMessage(_Out):
    type: Literal["error"] = "error"
    code: str
    message: str
    job_id: str | None = None
    request_id: str | None = None


class DoneMessage(_JobMessage):
    type: Literal["done"] = "done"
    state: Literal["done", "failed", "cancelled"]


class PongMessage(_Out):
    type: Literal["pong"] = "pong"
    request_id: str | None = None


class LiveResultMessage(_Out):
    """The answer to a ``live`` message, from the flow alone (``amortised.answer.live``): no rollout."""

    type: Literal["live-result"] = "live-result"
    request_id: str | None = None
    heatmap: dict | None = Field(None, description="min, max, cells, probability[j][i] of the start "
                                                   "positions over the start area (as heatmap.json)")
    samples: list[list[float]] = Field(description="start positions [x, y, z] drawn from the flow")
    most_probable: dict = Field(description="the flow's likeliest draw as an initial_state")
    fitted: bool = Field(description="false where the observation lies outside the training observations")
    draws: int = Field(description="draws from the flow behind the heatmap")
    model: str = Field(description="the model's fingerprint (what it was trained for)")
    seconds: float = Field(description="the answer's computation, from its turn to its reply")


ServerMessage = Annotated[Union[AcceptedMessage, ProgressMessage, TrajectoryMessage, HeatmapMessage,
                                ResultMessage, ErrorMessage, DoneMessage, PongMessage, LiveResultMessage],
                          Field(discriminator="type")]
SERVER_MESSAGE = TypeAdapter(ServerMessage)


# ---------------------------------------------------------------- REST bodies
class ErrorInfo(BaseModel):
    code: str
    message: str


class ErrorBody(ErrorInfo):
    """Every REST error: ``{"code": ..., "message": ...}``."""


class JobCreated(BaseModel):
    job_id: str
    state: JobState
    url: str = Field(description="GET it for the job's state")


class JobStatus(BaseModel):
    """``GET /jobs/{id}``; also the job's record in the job store."""

    job_id: str
    kind: JobKind
    state: JobState
    created_at: float = Field(description="Unix time")
    started_at: float | None = None
    finished_at: float | None = None
    queue_position: int | None = None
    progress: ProgressData | None = None
    summary: dict | None = Field(None, description="result summary once done")
    error: ErrorInfo | None = None
    scene: dict = Field(default_factory=dict, description="where the scene came from")
    overrides: dict = Field(default_factory=dict)
    artefacts: dict[str, str] = Field(default_factory=dict, description="artefact name -> URL")


class Health(BaseModel):
    status: Literal["ok"]
    version: str
    workers: int
    workers_ready: int
    executor: str
    queued: int
    running: int
    queue_size: int


def first_error_line(exc) -> str:
    """One line out of a pydantic ValidationError: the first problem, with its location."""
    errors = exc.errors(include_url=False)
    if not errors:
        return str(exc).splitlines()[0]
    err = errors[0]
    loc = ".".join(str(p) for p in err.get("loc", ()))
    msg = err.get("msg", "invalid")
    msg = msg.removeprefix("Value error, ")
    line = f"{loc}: {msg}" if loc else msg
    if len(errors) > 1:
        line += f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})"
    return line


def encode(message: BaseModel) -> str:
    """A message as compact JSON text: ``type``, ``job_id`` and ``request_id`` first, absent fields
    left out, NaN and infinities as null."""
    data = json.loads(message.model_dump_json(exclude_none=True))
    head = {key: data.pop(key) for key in ("type", "job_id", "request_id") if key in data}
    return json.dumps({**head, **data}, separators=(",", ":"), allow_nan=False)
