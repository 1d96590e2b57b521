"""Who may talk to the server: the ``Origin`` of browsers, the ``Host`` they asked for, a token.

``shared/spec/protocol.md``, "Access". One ASGI middleware in front of every
route, REST and WebSocket alike, checks in this order:

1. ``Host`` (only where ``ServerConfig.allowed_hosts`` is set: ``dejaview
   serve`` on a loopback address sets it to the loopback names): a page whose
   own name was made to resolve to 127.0.0.1 (DNS rebinding) is refused, 403
   ``forbidden_host``.
2. ``Origin``, when the request has one (browsers send it; scripts, the
   ``dejaview client`` and the Unreal client do not): it must be the server's
   own origin (scheme and ``Host`` of the request) or one of
   ``ServerConfig.allow_origins``; otherwise 403 ``forbidden_origin``, and a
   WebSocket handshake is refused with HTTP 403.
3. The token, when the server has one (``ServerConfig.token``; ``dejaview
   serve`` always has one on a non-loopback address): ``Authorization: Bearer
   TOKEN`` on any request, or ``?token=TOKEN`` in the URL of a WebSocket
   handshake (the JSON protocol and the bare-text mode alike: not every client
   can set headers) or of a ``GET`` / ``HEAD`` (how a browser opens the viewer:
   ``http://HOST:PORT/?token=TOKEN``; the page passes the token on to the
   files it loads). A missing or wrong token gets 401 ``unauthorized`` (REST)
   or, on the WebSocket, an accepted connection closed at once with code 4401
   and nothing else. ``GET /health`` needs no token (liveness checks).
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import urllib.parse

CLOSE_UNAUTHORIZED = 4401
PUBLIC_PATHS = {"/health"}  # GET / HEAD without a token
DEFAULT_PORTS = {"http": 80, "https": 443}
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def is_loopback(host: str) -> bool:
    """Whether a listening address reaches this machine only (``127.0.0.1``, ``::1``, ``localhost``)."""
    name = host.strip().strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False  # a host name other than localhost: may resolve to anything


def normalize_origin(origin: str) -> str | None:
    """``scheme://host[:port]``, lower case, default port left out; None when it is not one
    (``null``, a path, another scheme...)."""
    try:
        parts = urllib.parse.urlsplit(origin.strip())
        port = parts.port
    except ValueError:
        return None
    scheme = parts.scheme.lower()
    host = (parts.hostname or "").lower()
    if scheme not in DEFAULT_PORTS or not host or parts.path not in ("", "/") or parts.query or parts.username:
        return None
    if ":" in host:
        host = f"[{host}]"
    return f"{scheme}://{host}" if port in (None, DEFAULT_PORTS[scheme]) else f"{scheme}://{host}:{port}"


def host_name(host_header: str) -> str:
    """The name of a ``Host`` header, without port or IPv6 brackets, lower case."""
    host = host_header.strip().lower()
    if host.startswith("["):
        return host[1:host.find("]")] if "]" in host else host[1:]
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def _clip(text: str, n: int = 80) -> str:
    return text if len(text) <= n else text[:n] + "..."


class AccessControl:
    """ASGI middleware: the Host, Origin and token checks of the module docstring.

    Args:
        app: the application behind it.
        token: the token every request (but ``/health``) must carry; None: no token needed.
        allow_origins: normalized origins accepted besides the server's own.
        allowed_hosts: host names accepted in ``Host``; None: any.
    """

    def __init__(self, app, token: str | None = None, allow_origins=(), allowed_hosts=None):
        self.app = app
        self.token = token.encode() if token else None
        self.allow_origins = set(allow_origins)
        self.allowed_hosts = None if allowed_hosts is None else {h.lower() for h in allowed_hosts}

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {}
        for key, value in scope.get("headers") or ():
            headers.setdefault(key.decode("latin-1").lower(), value.decode("latin-1"))
        host = headers.get("host")
        if self.allowed_hosts is not None and host is not None and host_name(host) not in self.allowed_hosts:
            return await self._forbid(scope, receive, send, "forbidden_host",
                                      f"Host {_clip(host)!r} is not a name of this server (it listens on a "
                                      f"loopback address: use localhost or 127.0.0.1, or add the name's origin "
                                      f"with --allow-origin)")
        origin = headers.get("origin")
        if origin is not None and not self._origin_ok(origin, scope, host):
            return await self._forbid(scope, receive, send, "forbidden_origin",
                                      f"Origin {_clip(origin)!r} may not use this server (only its own "
                                      f"pages, and origins given with --allow-origin, may)")
        if self.token is not None and not self._public(scope) and not self._token_ok(scope, headers):
            return await self._unauthorized(scope, receive, send)
        return await self.app(scope, receive, send)

    # ------------------------------------------------------------ checks
    def _origin_ok(self, origin: str, scope, host: str | None) -> bool:
        if origin.strip() in self.allow_origins:  # e.g. "null", given on purpose
            return True
        normalized = normalize_origin(origin)
        if normalized is None:
            return False
        if normalized in self.allow_origins:
            return True
        if host is None:
            return False
        scheme = {"ws": "http", "wss": "https"}.get(scope.get("scheme", "http"), scope.get("scheme", "http"))
        return normalized == normalize_origin(f"{scheme}://{host}")

    @staticmethod
    def _public(scope) -> bool:
        return scope["type"] == "http" and scope.get("method") in ("GET", "HEAD") and scope["path"] in PUBLIC_PATHS

    def _token_ok(self, scope, headers: dict) -> bool:
        auth = headers.get("authorization", "")
        scheme, _, given = auth.partition(" ")
        if scheme.lower() == "bearer" and self._same(given.strip()):
            return True
        if scope["type"] == "websocket" or scope.get("method") in ("GET", "HEAD"):
            query = urllib.parse.parse_qs(scope.get("query_string", b"").decode("latin-1"))
            return any(self._same(value) for value in query.get("token", ())[:4])
        return False

    def _same(self, given: str) -> bool:
        return hmac.compare_digest(given.encode("utf-8", "surrogateescape"), self.token)

    # ------------------------------------------------------------ answers
    async def _forbid(self, scope, receive, send, code: str, message: str):
        if scope["type"] == "websocket":
            await receive()  # websocket.connect
            # a close before the accept: the handshake is answered with HTTP 403
            await send({"type": "websocket.close", "code": 1008, "reason": code})
            return
        await _json(send, 403, code, message)

    async def _unauthorized(self, scope, receive, send):
        if scope["type"] == "websocket":
            await receive()  # websocket.connect
            await send({"type": "websocket.accept"})
            await send({"type": "websocket.close", "code": CLOSE_UNAUTHORIZED, "reason": "unauthorized"})
            return
        await _json(send, 401, "unauthorized",
                    "missing or wrong token: send 'Authorization: Bearer TOKEN' (or, WebSocket and GET, "
                    "'?token=TOKEN' in the URL)", [(b"www-authenticate", b'Bearer realm="dejaview"')])


async def _json(send, status: int, code: str, message: str, headers=()):
    body = json.dumps({"code": code, "message": message}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *headers]})
    await send({"type": "http.response.body", "body": body})
