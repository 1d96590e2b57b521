"""Exception types shared by every part of DejaView."""

from __future__ import annotations


class DejaViewError(Exception):
    """Base class of every error DejaView raises on purpose."""


class SceneError(DejaViewError):
    """A scene file (or scene text) that cannot be used.

    The message always names where the problem is: ``file:line: <element>: reason``.

    Attributes:
        reason: the one-line reason, without location.
        file: scene file name (or ``"<string>"``), may be None.
        line: 1-based line number, may be None.
        element: tag of the offending element, may be None.
    """

    def __init__(self, reason: str, file: str | None = None, line: int | None = None,
                 element: str | None = None):
        self.reason = reason
        self.file = file
        self.line = line
        self.element = element
        super().__init__(self._format())

    def _format(self) -> str:
        where = self.file or "<scene>"
        if self.line is not None:
            where += f":{self.line}"
        elem = f" <{self.element}>" if self.element else ""
        return f"{where}:{elem} {self.reason}".replace(": ", ": ", 1)


class GeometryError(DejaViewError):
    """A mesh or sphere packing that cannot be loaded or used."""


class SimulationError(DejaViewError):
    """Invalid simulation input (e.g. non-finite state) or settings."""


class InferenceError(DejaViewError):
    """Invalid inference settings or a problem that cannot be optimised."""


class StartAreaError(SceneError, InferenceError):
    """A start area that cannot hold the source: inside other objects everywhere, or beyond the
    bounds of positions (``dejaview.inference.start_area``). Both a scene error (it names the
    element, as ``dejaview validate`` does) and an inference error (what ``solve`` raises)."""


class ResourceError(DejaViewError):
    """A request sized over what the machine allows (``dejaview.memory``), refused before it runs.

    The message is ``"<request> <detail>"``: what was asked, then the estimate and the limit.

    Attributes:
        request: words naming what was asked (``"8000000 posterior samples"``).
        detail: the rest of the line (the estimate and the limit).
        need: the estimated peak in bytes (what the process held plus the request's estimate).
        limit: the limit in bytes.
    """

    def __init__(self, request: str, detail: str = "", need: int | None = None, limit: int | None = None):
        self.request, self.detail, self.need, self.limit = request, detail, need, limit
        super().__init__(f"{request} {detail}".strip())

    def naming(self, request: str) -> "ResourceError":
        """The same refusal, the request named as its caller knows it (a heatmap's cells for the
        posterior samples its solve draws)."""
        return ResourceError(request, self.detail, self.need, self.limit)


class OutputError(DejaViewError):
    """A result set that could not be written (a full disk, no permission): nothing of it was put
    in place (``dejaview.result_set``).

    Attributes:
        path: the file or folder that could not be written.
        errno: the operating system's error number, or None.
    """

    def __init__(self, message: str, path=None, errno: int | None = None):
        self.path, self.errno = path, errno
        super().__init__(message)
