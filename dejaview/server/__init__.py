"""The DejaView service: FastAPI REST and WebSocket for the VR client, scripts and the web viewer.

``create_app(config)`` (``dejaview.server.app``) is the application;
``dejaview serve`` runs it under uvicorn. Contract: ``shared/spec/protocol.md``.

- ``messages``: the typed messages (one discriminated union per direction), REST bodies, error codes;
- ``scenes``: scene input (XML text or a path inside the scene root) and its checks;
- ``runner``: the job queue, records on disk, subscribers; ``workers``: the worker pools;
  ``jobs``: what a worker does with a job;
- ``websocket``: the ``/ws`` endpoint (JSON and bare-text modes); ``limits``: size and rate limits;
- ``client``: the Python client behind ``dejaview client``, the tests and ``bench/load.py``.
"""

from __future__ import annotations


def __getattr__(name):
    # fastapi loads on first use, not on ``import dejaview.server.client``
    if name == "create_app":
        from dejaview.server.app import create_app

        return create_app
    if name == "ServerConfig":
        from dejaview.server.config import ServerConfig

        return ServerConfig
    raise AttributeError(f"module 'dejaview.server' has no attribute {name!r}")


__all__ = ["ServerConfig", "create_app"]
