"""A Python client of the DejaView service (what ``dejaview client``, the tests and the load
benchmark use).

``run_job`` submits one job over the WebSocket, follows its messages to
``done`` and saves the artefacts: inline payloads as they come, the rest
(and ``heatmap.png``) fetched over REST from their URLs::

    from dejaview.server.client import run_job
    outcome = run_job("ws://127.0.0.1:8765/ws", "solve", scene_path="ball.xml", out_dir="out")
    outcome.state, outcome.files["trajectory.csv"], outcome.result["loss"]

``submit_job`` is the same as a coroutine, for many clients at once. A server that needs a
token gets it with ``token=`` (the ``?token=`` of the WebSocket URL, a Bearer header on REST).
"""

from __future__ import annotations

import asyncio
import json
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from dejaview.errors import DejaViewError
from dejaview.server.access import CLOSE_UNAUTHORIZED



class ClientError(DejaViewError):
    """The server refused or failed the job, or could not be reached (one line)."""

    def __init__(self, message: str, code: str | None = None, outcome: "JobOutcome | None" = None):
        self.code = code
        self.outcome = outcome
        super().__init__(message)


@dataclass
class JobOutcome:
    """What became of one submitted job.

    Attributes:
        job_id: the server's id (None when the submission was refused).
        state: ``done``, ``failed``, ``cancelled`` or ``refused``.
        messages: every message received about the job, in order (dicts).
        files: artefact name -> saved path (with ``out_dir``).
        csv: the trajectory CSV text (inline or fetched).
        result: the result JSON (solve, heatmap), if any.
        error: the ``error`` message, if any.
        latency_s: seconds from sending ``submit`` to ``done``.
    """

    job_id: str | None = None
    state: str | None = None
    messages: list[dict] = field(default_factory=list)
    files: dict[str, Path] = field(default_factory=dict)
    csv: str | None = None
    ppm: str | None = None
    result: dict | None = None
    error: dict | None = None
    latency_s: float | None = None

    def of_type(self, kind: str) -> list[dict]:
        return [m for m in self.messages if m.get("type") == kind]


def http_base(ws_url: str) -> str:
    """``ws://host:port/ws`` -> ``http://host:port`` (``wss`` -> ``https``)."""
    parts = urllib.parse.urlsplit(ws_url)
    scheme = {"ws": "http", "wss": "https"}.get(parts.scheme, parts.scheme)
    return urllib.parse.urlunsplit((scheme, parts.netloc, "", "", "")).rstrip("/")


def with_token(url: str, token: str | None) -> str:
    """``url`` with ``token=TOKEN`` added to its query (how a WebSocket client carries the token)."""
    if not token:
        return url
    parts = urllib.parse.urlsplit(url)
    query = urllib.parse.parse_qsl(parts.query, keep_blank_values=True)
    query = [(k, v) for k, v in query if k != "token"] + [("token", token)]
    return urllib.parse.urlunsplit(parts._replace(query=urllib.parse.urlencode(query)))


def http_get(url: str, timeout: float = 30.0, token: str | None = None) -> bytes:
    """GET a URL (with ``Authorization: Bearer TOKEN`` when a token is given); raises
    ClientError with the server's one-line message on an HTTP error."""
    request = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.read()
    except urllib.error.HTTPError as exc:
        try:
            body = json.loads(exc.read())
            raise ClientError(f"GET {url}: {exc.code} {body.get('code')}: {body.get('message')}",
                              body.get("code")) from None
        except (ValueError, AttributeError):
            raise ClientError(f"GET {url}: HTTP {exc.code}") from None
    except (urllib.error.URLError, OSError) as exc:
        raise ClientError(f"GET {url}: {getattr(exc, 'reason', exc)}") from None


def get_json(url: str, timeout: float = 30.0, token: str | None = None):
    return json.loads(http_get(url, timeout, token))


def wait_healthy(base: str, timeout: float = 60.0) -> dict:
    """Poll ``GET base/health`` until it answers ok; returns its body.

    Raises:
        ClientError: no healthy answer within ``timeout`` seconds.
    """
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            body = get_json(f"{base}/health", timeout=5.0)
            if body.get("status") == "ok":
                return body
        except ClientError as exc:
            last = exc
        time.sleep(0.1)
    raise ClientError(f"{base} is not healthy after {timeout:g} s ({last})")


async def _fetch(url: str, token: str | None = None) -> bytes:
    return await asyncio.to_thread(http_get, url, 30.0, token)


async def submit_job(url: str, kind: str, *, scene_xml: str | None = None, scene_path: str | None = None,
                     overrides: dict | None = None, out_dir=None, request_id: str | None = None,
                     on_message=None, cancel_when=None, fetch: bool = True,
                     timeout: float | None = None, open_timeout: float = 10.0,
                     token: str | None = None) -> JobOutcome:
    """Submit a job over the WebSocket at ``url`` and follow it to ``done``.

    Args:
        url: ``ws://host:port/ws``.
        kind: ``simulate``, ``solve`` or ``heatmap``.
        scene_xml / scene_path: the scene as text, or a path inside the server's scene root.
        overrides: e.g. ``{"iterations": 20}``.
        out_dir: save trajectory.csv, result.json, heatmap.ppm / .png / .json here.
        on_message: called with every message (dict) about the job (progress bars).
        cancel_when: called with every message; True sends ``cancel`` for the job (once).
        fetch: fetch payloads sent as URLs only (and heatmap.png) over REST.
        timeout: seconds for the whole job (None: no limit).
        token: the server's token (sent as ``?token=`` on the WebSocket, as a Bearer header on REST).
    Returns:
        JobOutcome; ``state`` is ``refused`` when the server answered the submit with an error.
    Raises:
        ClientError: the server cannot be reached, or closed the connection before ``done``.
    """
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus, InvalidURI

    request_id = request_id or uuid.uuid4().hex[:12]
    message = {"type": "submit", "kind": kind, "request_id": request_id}
    message.update({"scene_xml": scene_xml} if scene_xml is not None else {"scene_path": scene_path})
    if overrides:
        message["overrides"] = overrides
    out = Path(out_dir) if out_dir is not None else None
    outcome = JobOutcome()
    base = http_base(url)

    def save(name: str, data: bytes | str) -> None:
        if out is None:
            return
        out.mkdir(parents=True, exist_ok=True)
        path = out / name
        if isinstance(data, str):
            path.write_text(data, encoding="utf-8")
        else:
            path.write_bytes(data)
        outcome.files[name] = path

    async def payload(inline, link):
        if inline is not None:
            return inline if isinstance(inline, str) else json.dumps(inline, indent=2)
        if link and fetch:
            return (await _fetch(link if "://" in link else base + link, token)).decode("utf-8")
        return None

    async def follow():
        try:
            websocket = await connect(with_token(url, token), max_size=None, open_timeout=open_timeout)
        except InvalidStatus as exc:
            status = exc.response.status_code
            why = " (this client's origin is not allowed)" if status == 403 else ""
            raise ClientError(f"cannot connect to {url}: the server refused the connection with HTTP "
                              f"{status}{why}", "forbidden" if status == 403 else None) from None
        except (OSError, InvalidHandshake, InvalidURI, asyncio.TimeoutError) as exc:
            raise ClientError(f"cannot connect to {url}: {exc}") from None
        cancelled = False
        start = time.perf_counter()
        try:
            await websocket.send(json.dumps(message))
            async for raw in websocket:
                if not isinstance(raw, str):
                    continue
                msg = json.loads(raw)
                mine = msg.get("request_id") == request_id or (
                    outcome.job_id is not None and msg.get("job_id") == outcome.job_id)
                if not mine:
                    continue
                outcome.messages.append(msg)
                if on_message is not None:
                    on_message(msg)
                kind_ = msg.get("type")
                if kind_ == "accepted":
                    outcome.job_id = msg["job_id"]
                elif kind_ == "error":
                    outcome.error = msg
                    if outcome.job_id is None:
                        outcome.state = "refused"
                        break
                elif kind_ == "trajectory":
                    outcome.csv = await payload(msg.get("csv"), msg.get("url"))
                    if outcome.csv is not None:
                        save("trajectory.csv", outcome.csv)
                elif kind_ == "heatmap":
                    outcome.ppm = await payload(msg.get("ppm"), msg.get("ppm_url"))
                    if outcome.ppm is not None:
                        save("heatmap.ppm", outcome.ppm)
                    grid = await payload(msg.get("grid"), msg.get("grid_url"))
                    if grid is not None:
                        save("heatmap.json", grid)
                    if fetch and out is not None and msg.get("png_url"):
                        save("heatmap.png", await _fetch(msg["png_url"], token))
                elif kind_ == "result":
                    text = await payload(msg.get("result"), msg.get("url"))
                    if text is not None:
                        outcome.result = json.loads(text)
                        save("result.json", json.dumps(outcome.result, indent=2))
                elif kind_ == "done":
                    outcome.state = msg["state"]
                    break
                if cancel_when is not None and not cancelled and outcome.job_id and cancel_when(msg):
                    cancelled = True
                    await websocket.send(json.dumps({"type": "cancel", "job_id": outcome.job_id,
                                                     "request_id": request_id}))
            else:
                raise ClientError(f"the server closed the connection before job {outcome.job_id} was done")
        except ConnectionClosed as exc:
            if exc.rcvd is not None and exc.rcvd.code == CLOSE_UNAUTHORIZED:
                raise ClientError(f"{url}: the server wants a token and " + (
                    "refused this one" if token else "none was given (--token or DEJAVIEW_TOKEN)")
                    + " (WebSocket close code 4401)", "unauthorized") from None
            raise ClientError(f"the server closed the connection before job {outcome.job_id} was done "
                              f"({exc})", outcome=outcome) from None
        finally:
            await websocket.close()
        outcome.latency_s = time.perf_counter() - start
        return outcome

    if timeout is None:
        return await follow()
    try:
        return await asyncio.wait_for(follow(), timeout)
    except asyncio.TimeoutError:
        raise ClientError(f"job {outcome.job_id} not done after {timeout:g} s", outcome=outcome) from None


def run_job(url: str, kind: str, **kwargs) -> JobOutcome:
    """``submit_job`` for synchronous code (one event loop per call)."""
    return asyncio.run(submit_job(url, kind, **kwargs))
