"""The FastAPI application: REST routes, the WebSocket endpoint, limits and error bodies.

``create_app(config)`` builds one app around one ``JobRunner``; the runner's
workers start with the app (its lifespan) and stop with it. REST errors are
``{"code": ..., "message": ...}`` with the status listed in
``dejaview.server.messages``; the OpenAPI page is at ``/docs`` and includes
the WebSocket message schemas (``ClientMessage``, ``ServerMessage``). The web viewer is served
at ``/`` (``dejaview.server.viewer``). Origin, Host and token checks come before everything
(``dejaview.server.access``).
"""

from __future__ import annotations

import contextlib
import enum

from fastapi import FastAPI, Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from dejaview import __version__
from dejaview.server.access import AccessControl
from dejaview.server.config import ServerConfig
from dejaview.server.errors import ServiceError
from dejaview.server.limits import BodyLimit
from dejaview.server.live import LiveAnswers
from dejaview.server.messages import (
    CLIENT_MESSAGE,
    SERVER_MESSAGE,
    ErrorBody,
    Health,
    JobCreated,
    JobRequest,
    JobStatus,
)
from dejaview.server.runner import ARTEFACTS, JobRunner
from dejaview.server.viewer import add_viewer_routes
from dejaview.server.websocket import Connection

Artefact = enum.Enum("Artefact", {name.replace(".", "_"): name for name in ARTEFACTS}, type=str)

ERRORS = {status: {"model": ErrorBody} for status in (400, 401, 403, 404, 409, 413, 422, 503)}


def _error(code: str, message: str, status: int) -> JSONResponse:
    return JSONResponse({"code": code, "message": message}, status_code=status)


def _absolute(request: Request, status: JobStatus) -> JobStatus:
    base = str(request.base_url).rstrip("/")
    return status.model_copy(update={"artefacts": {k: base + v for k, v in status.artefacts.items()}})


def create_app(config: ServerConfig | None = None, **settings) -> FastAPI:
    """The DejaView service.

    Args:
        config: a ServerConfig; or give its fields as keyword arguments
            (``scene_root=``, ``results_dir=``, ``workers=``...), which also override ``config``.
    """
    if config is None:
        config = ServerConfig(**settings)
    elif settings:
        config = config.replace(**settings)
    runner = JobRunner(config)
    live = LiveAnswers(config)

    @contextlib.asynccontextmanager
    async def lifespan(app):
        await runner.start()
        try:
            yield
        finally:
            live.close()
            await runner.close()

    app = FastAPI(title="DejaView", version=__version__, lifespan=lifespan,
                  description="Simulate scenes, infer where an object came from (solve), map where it "
                              "could have started (heatmap), train an amortised model of a scene (train) and "
                              "answer its observations live (the WebSocket's `live`). REST for scripts; the WebSocket `/ws` "
                              "speaks the typed messages `ClientMessage` / `ServerMessage` listed below.")
    app.state.config = config
    app.state.runner = runner
    app.state.live = live
    app.add_middleware(BodyLimit, max_bytes=config.max_body_bytes)
    # added last, so it runs first: nothing is read from a client that may not use the server
    app.add_middleware(AccessControl, token=config.token, allow_origins=config.allow_origins,
                       allowed_hosts=config.allowed_hosts)

    @app.exception_handler(ServiceError)
    async def service_error(request, exc: ServiceError):
        return _error(exc.code, exc.message, exc.status)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request, exc: RequestValidationError):
        errors = exc.errors()
        if any(e.get("type") == "json_invalid" for e in errors):
            return _error("invalid_json", "the request body is not valid JSON", 400)
        first = errors[0] if errors else {}
        loc = ".".join(str(p) for p in first.get("loc", ()) if p != "body")
        msg = str(first.get("msg", "invalid request")).removeprefix("Value error, ")
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        return _error("invalid_message", f"{loc}: {msg}{more}" if loc else f"{msg}{more}", 422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request, exc: StarletteHTTPException):
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        return _error(code, str(exc.detail), exc.status_code)

    @app.get("/health", response_model=Health, summary="Is the server up?")
    async def health():
        pool = runner.pool
        return Health(status="ok", version=__version__, workers=config.workers,
                      workers_ready=getattr(pool, "ready", 0), executor=config.executor,
                      queued=len(runner.pending), running=runner.running, queue_size=config.queue_size)

    @app.post("/jobs", status_code=202, response_model=JobCreated, responses=ERRORS,
              summary="Submit a simulate, solve, heatmap or train job")
    async def submit_job(body: JobRequest, request: Request):
        overrides = body.overrides.given() if body.overrides else {}
        job = await runner.submit_request(body.kind, scene_xml=body.scene_xml, scene_path=body.scene_path,
                                          overrides=overrides)
        return JobCreated(job_id=job.id, state=job.status.state,
                          url=str(request.url_for("get_job", job_id=job.id)))

    @app.get("/jobs/{job_id}", response_model=JobStatus, responses=ERRORS,
             summary="State, progress and result summary of a job")
    async def get_job(job_id: str, request: Request):
        return _absolute(request, runner.status(job_id))

    @app.get("/jobs/{job_id}/model", response_class=FileResponse, responses=ERRORS,
             summary="The model file a finished train job wrote (safetensors, for solve --amortised)")
    async def get_model(job_id: str):
        path = runner.model(job_id)  # before the artefact route: "model" is not an artefact's name
        return FileResponse(path, media_type="application/octet-stream", filename=path.name)

    @app.get("/jobs/{job_id}/{artefact}", response_class=FileResponse, responses=ERRORS,
             summary="An artefact of a finished job: trajectory.csv, heatmap.ppm, heatmap.png, result.json...")
    async def get_artefact(job_id: str, artefact: Artefact):
        path = runner.artefact(job_id, artefact.value)
        return FileResponse(path, media_type=ARTEFACTS[artefact.value], filename=artefact.value,
                            content_disposition_type="inline")

    @app.delete("/jobs/{job_id}", status_code=202, response_model=JobStatus, responses=ERRORS,
                summary="Cancel a job (a running one stops within one iteration)")
    async def cancel_job(job_id: str, request: Request):
        return _absolute(request, runner.cancel(job_id))

    @app.websocket("/ws")
    async def websocket(ws: WebSocket):
        await Connection(ws, runner, config, live).run()

    def openapi():
        if app.openapi_schema is None:
            from fastapi.openapi.utils import get_openapi

            schema = get_openapi(title=app.title, version=app.version, description=app.description,
                                 routes=app.routes)
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for name, adapter in (("ClientMessage", CLIENT_MESSAGE), ("ServerMessage", SERVER_MESSAGE)):
                sub = adapter.json_schema(ref_template="#/components/schemas/{model}")
                for key, value in sub.pop("$defs", {}).items():
                    components.setdefault(key, value)
                components[name] = sub
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi
    add_viewer_routes(app, config.scene_root, config.token)
    return app
