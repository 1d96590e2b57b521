"""The WebSocket endpoint ``/ws``: typed JSON messages, and the original client's bare-text mode.

JSON mode (``shared/spec/protocol.md``): every frame is a JSON object with a
``type`` (``dejaview.server.messages``). A session (ids shortened)::

    -> {"type":"submit","kind":"solve","scene_path":"ball.xml","overrides":{"iterations":3},
        "request_id":"r1"}
    <- {"type":"accepted","job_id":"e236...","request_id":"r1","kind":"solve","state":"queued",
        "queue_position":1}
    <- {"type":"progress","job_id":"e236...","request_id":"r1","iteration":1,"total":3,
        "loss":0.1229,"best_loss":0.1229,"elapsed_s":0.31,"evaluations":1}
    <- {"type":"progress", ... "iteration":3,"total":3,"loss":0.0851,"best_loss":0.0851, ...}
    <- {"type":"trajectory","job_id":"e236...","request_id":"r1",
        "csv":"step,time,object,x,y,z,qw,qx,qy,qz\\n0,0.000000,ball,...",
        "url":"http://127.0.0.1:8765/jobs/e236.../trajectory.csv","bytes":1333}
    <- {"type":"result","job_id":"e236...","request_id":"r1","result":{"source":"ball",
        "loss":0.0851,...},"url":"http://127.0.0.1:8765/jobs/e236.../result.json"}
    <- {"type":"done","job_id":"e236...","request_id":"r1","state":"done"}

Bad input never closes the connection: it is answered with an ``error``
message (with the ``request_id`` when one could be read) and the connection
goes on. Frames are dropped with one ``rate_limited`` error per second when a
connection sends faster than its rate; messages over ``max_message_bytes``
get ``message_too_large`` (over 4x that the WebSocket layer closes the
connection, code 1009). A client that disconnects leaves its jobs running;
their results stay available over REST (and through ``subscribe``).

Bare-text mode (the original Unreal client): a text frame that is not JSON is
the path of a scene file inside the scene root. The scene decides the job: no
``<inference>``: simulate; ``<inference>``: solve; ``<inference>`` with a
``<heatmap>``: heatmap. When the job ends the answer is bare text frames:
the trajectory CSV, then (heatmap jobs) the PPM P3 image. Payloads are sent
whole (the old client cannot follow URLs) up to ``max_bare_bytes``. An error
in this mode is one bare text frame starting with ``error:``, e.g.
``error: scene_path 'missing.xml': no such file in the scene root``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re

from pydantic import ValidationError
from starlette.websockets import WebSocket, WebSocketDisconnect

from dejaview.server.errors import ServiceError, from_library_error
from dejaview.server.limits import TokenBucket
from dejaview.server.live import LiveQueue
from dejaview.server.messages import (
    CLIENT_MESSAGE,
    CancelMessage,
    ErrorMessage,
    LiveMessage,
    PingMessage,
    PongMessage,
    ProgressMessage,
    SubmitMessage,
    SubscribeMessage,
    encode,
    first_error_line,
)
from dejaview.server.scenes import read_scene_input

log = logging.getLogger("dejaview.server")

URL_FIELDS = ("url", "ppm_url", "png_url", "grid_url")
MAX_QUEUED_PROGRESS = 256  # progress for a slow reader beyond this is dropped (final messages never)
# a frame that starts as a live message draws on the live budget (read before any parsing)
LIVE_FRAME = re.compile(r'\s*\{\s*"type"\s*:\s*"live"')


def _reject_constant(name):
    raise ValueError(f"{name} is not valid JSON")


def parse_json(text: str):
    """``json.loads`` without NaN / Infinity (which JSON does not have)."""
    return json.loads(text, parse_constant=_reject_constant)


def looks_like_json(text: str) -> bool:
    """Whether a frame is meant as JSON (else it is a bare-text scene path)."""
    stripped = text.strip()
    if stripped[:1] in ("{", "["):
        return True
    try:
        parse_json(stripped)
    except (ValueError, RecursionError):
        return False
    return True


class Connection:
    """One WebSocket client: reads its frames, runs its requests, sends its messages in order."""

    def __init__(self, websocket: WebSocket, runner, config, live=None):
        self.ws = websocket
        self.runner = runner
        self.config = config
        self.out: asyncio.Queue = asyncio.Queue()
        self.bucket = TokenBucket(config.messages_per_second)
        self.live_bucket = TokenBucket(config.live_messages_per_second)
        self.live = None if live is None else LiveQueue(live.answer, self.send, self._live_failed)
        self.last_rate_error = -1e9
        self.dropped = 0
        self.following: set[str] = set()  # jobs whose messages come here
        self.active: set[str] = set()  # unfinished jobs submitted here
        self.bare = BareReplies(self)
        base = str(websocket.base_url).rstrip("/")
        self.http_base = base.replace("ws://", "http://", 1).replace("wss://", "https://", 1)

    # ------------------------------------------------------------ main loop
    async def run(self) -> None:
        await self.ws.accept()
        sender = asyncio.create_task(self._send_loop())
        try:
            while True:
                message = await self.ws.receive()
                if message["type"] == "websocket.disconnect":
                    break
                text, data = message.get("text"), message.get("bytes")
                live = text is not None and LIVE_FRAME.match(text) is not None
                if not (self.live_bucket if live else self.bucket).take():
                    self._rate_limited(live)
                    continue
                if text is None:
                    self.error("binary_frame", f"binary frames ({len(data or b'')} bytes) are not "
                                               "understood: send JSON text (or a bare scene path)")
                    continue
                await self._frame(text)
        except WebSocketDisconnect:
            pass
        finally:
            if self.live is not None:
                self.live.close()
            for job_id in list(self.following):
                self.runner.unsubscribe(job_id, self)
            for job_id in list(self.bare.jobs):
                self.runner.unsubscribe(job_id, self.bare)
            self.out.put_nowait(None)
            try:
                await asyncio.wait_for(sender, 1.0)
            except (asyncio.TimeoutError, Exception):
                sender.cancel()

    async def _send_loop(self) -> None:
        while True:
            text = await self.out.get()
            if text is None:
                return
            try:
                await self.ws.send_text(text)
            except Exception:  # the client is gone; the receive loop notices too
                return

    def send(self, message) -> None:
        if isinstance(message, ProgressMessage) and self.out.qsize() > MAX_QUEUED_PROGRESS:
            return
        self.out.put_nowait(encode(message))

    def error(self, code: str, message: str, request_id=None, job_id=None) -> None:
        if not _utf8(message):  # a client's text echoed into the message may hold lone surrogates
            message = message.encode("utf-8", "replace").decode("utf-8")
        if isinstance(request_id, str) and not _utf8(request_id):
            request_id = None
        self.send(ErrorMessage(code=code, message=message, request_id=request_id, job_id=job_id))

    def _rate_limited(self, live: bool = False) -> None:
        self.dropped += 1
        now = self.bucket.clock()
        if now - self.last_rate_error >= 1.0:
            self.last_rate_error = now
            rate = self.config.live_messages_per_second if live else self.config.messages_per_second
            what = "live messages" if live else "messages"
            self.error("rate_limited", f"more than {rate:g} {what} per second: {self.dropped} message(s) "
                                       f"dropped so far")

    # ------------------------------------------------------------ frames
    async def _frame(self, text: str) -> None:
        size = len(text.encode("utf-8", errors="surrogatepass"))
        if size > self.config.max_message_bytes:
            self.error("message_too_large", f"message is {size} bytes, over the limit of "
                                            f"{self.config.max_message_bytes} bytes")
            return
        if not looks_like_json(text):
            await self._bare(text)
            return
        try:
            data = parse_json(text)
        except (ValueError, RecursionError) as exc:
            self.error("invalid_json", f"not valid JSON: {' '.join(str(exc).split())}"[:300])
            return
        request_id = data.get("request_id") if isinstance(data, dict) else None
        if not isinstance(request_id, str) or len(request_id) > 200:
            request_id = None
        if not isinstance(data, dict):
            self.error("invalid_message", f"a message is a JSON object with a 'type', not a "
                                          f"{type(data).__name__}")
            return
        try:
            message = CLIENT_MESSAGE.validate_python(data)
        except ValidationError as exc:
            kinds = {e["type"] for e in exc.errors(include_url=False)}
            code = "unknown_type" if "union_tag_invalid" in kinds else "invalid_message"
            if "union_tag_not_found" in kinds:
                self.error(code, "a message needs a 'type': submit, cancel, subscribe, ping or live", request_id)
            else:
                self.error(code, first_error_line(exc), request_id)
            return
        try:
            if isinstance(message, SubmitMessage):
                await self._submit(message)
            elif isinstance(message, CancelMessage):
                self.runner.cancel(message.job_id)
            elif isinstance(message, SubscribeMessage):
                self.runner.subscribe(message.job_id, self, message.request_id)
            elif isinstance(message, PingMessage):
                self.send(PongMessage(request_id=message.request_id))
            elif isinstance(message, LiveMessage):
                if self.live is None:
                    raise ServiceError("no_model", "this server answers no live messages")
                self.live.put(message)
        except ServiceError as exc:
            self.error(exc.code, exc.message, message.request_id, getattr(message, "job_id", None))
        except Exception as exc:  # a bug must not end the connection
            log.exception("error handling a WebSocket message")
            err = from_library_error(exc)
            self.error(err.code, err.message, message.request_id)

    async def _submit(self, message: SubmitMessage) -> None:
        if len(self.active) >= self.config.max_jobs_per_connection:
            raise ServiceError("too_many_jobs", f"this connection already has {len(self.active)} "
                                                f"unfinished jobs (the limit)", 429)
        overrides = message.overrides.given() if message.overrides else {}
        await self.runner.submit_request(message.kind, scene_xml=message.scene_xml,
                                         scene_path=message.scene_path, overrides=overrides,
                                         subscriber=self, request_id=message.request_id)

    def _live_failed(self, exc: Exception, message) -> None:
        err = exc if isinstance(exc, ServiceError) else from_library_error(exc)
        if not isinstance(exc, ServiceError):
            log.error("error answering a live message: %s", err.message)
        self.error(err.code, err.message, message.request_id)

    def deliver(self, job_id: str, message) -> None:
        """Subscriber callback: send a job's message with absolute URLs."""
        if message.type == "accepted":
            self.active.add(job_id)
        update = {}
        for name in URL_FIELDS:
            value = getattr(message, name, None)
            if isinstance(value, str) and value.startswith("/"):
                update[name] = self.http_base + value
        self.send(message.model_copy(update=update) if update else message)
        if message.type == "done":
            self.active.discard(job_id)
            self.following.discard(job_id)
        else:
            self.following.add(job_id)

    # ------------------------------------------------------------ bare-text mode
    async def _bare(self, text: str) -> None:
        name = text.strip()
        try:
            if len(self.active) >= self.config.max_jobs_per_connection:
                raise ServiceError("too_many_jobs", f"this connection already has {len(self.active)} "
                                                    f"unfinished jobs (the limit)")
            scene_input = await asyncio.to_thread(read_scene_input, self.config.scene_root, scene_path=name,
                                                  max_bytes=self.config.max_scene_bytes)
            inf = scene_input.scene.inference
            kind = "simulate" if inf is None else "heatmap" if inf.heatmap is not None else "solve"
            self.runner.submit(kind, scene_input, {}, subscriber=self.bare)
        except ServiceError as exc:
            self.out.put_nowait(f"error: {exc.message}")
        except Exception as exc:  # a bug must not end the connection
            log.exception("error handling a bare-text frame")
            self.out.put_nowait(f"error: {from_library_error(exc).message}")


class BareReplies:
    """The subscriber of a connection's bare-text jobs: answers each with bare text frames."""

    def __init__(self, connection: Connection):
        self.connection = connection
        self.jobs: set[str] = set()
        self.errors: dict[str, str] = {}

    def deliver(self, job_id: str, message) -> None:
        conn = self.connection
        if message.type == "accepted":
            self.jobs.add(job_id)
            conn.active.add(job_id)
        elif message.type == "error":
            self.errors[job_id] = message.message
        elif message.type == "done":
            self.jobs.discard(job_id)
            conn.active.discard(job_id)
            asyncio.get_running_loop().create_task(self._answer(job_id, message.state))

    async def _answer(self, job_id: str, state: str) -> None:
        conn = self.connection
        if state != "done":
            conn.out.put_nowait(f"error: {self.errors.pop(job_id, None) or f'the job was {state}'}")
            return
        frames = []
        for name in ("trajectory.csv", "heatmap.ppm"):
            try:
                path = conn.runner.artefact(job_id, name)
            except ServiceError:
                continue
            size = path.stat().st_size
            if size > conn.config.max_bare_bytes:
                frames = [f"error: {name} is {size} bytes, over the bare-text limit of "
                          f"{conn.config.max_bare_bytes} bytes; fetch {conn.http_base}/jobs/{job_id}/{name}"]
                break
            frames.append(await asyncio.to_thread(path.read_text, encoding="utf-8"))
        for frame in frames:
            conn.out.put_nowait(frame)


def _utf8(text: str) -> bool:
    """Whether ``text`` can be encoded as UTF-8 (JSON may carry lone surrogates that cannot)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True
