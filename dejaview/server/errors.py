"""The one exception type of the service: an error code, a one-line message and an HTTP status."""

from __future__ import annotations

from dejaview.errors import DejaViewError


class ServiceError(DejaViewError):
    """A request the server refuses (see ``dejaview.server.messages`` for the codes).

    Attributes:
        code: machine-readable error code (``invalid_scene``, ``queue_full``...).
        message: one line for a person.
        status: the HTTP status REST answers with.
    """

    def __init__(self, code: str, message: str, status: int = 400):
        self.code = code
        self.message = " ".join(str(message).split())
        self.status = status
        super().__init__(self.message)


# The library's errors as (code, HTTP status): bad scenes are the client's fault, the rest happen
# while a job runs.
LIBRARY_ERRORS = {
    "StartAreaError": ("infeasible_start_area", 422),  # before SceneError and InferenceError, its bases
    "SceneError": ("invalid_scene", 422),
    "GeometryError": ("geometry_error", 422),
    "SimulationError": ("simulation_error", 422),
    "InferenceError": ("inference_error", 422),
    "ResourceError": ("limit_exceeded", 422),  # sized over the memory limit (dejaview.memory)
    "OutputError": ("write_failed", 500),  # disk_full where the disk is full (write_error)
}


def from_library_error(exc: Exception) -> ServiceError:
    """The ServiceError for a DejaView library error (``internal_error`` for anything else)."""
    if isinstance(exc, OSError) or type(exc).__name__ == "OutputError":
        return write_error(exc)
    for cls in type(exc).__mro__:
        if cls.__name__ in LIBRARY_ERRORS:
            code, status = LIBRARY_ERRORS[cls.__name__]
            return ServiceError(code, str(exc), status)
    if isinstance(exc, ServiceError):
        return exc
    return ServiceError("internal_error", f"internal error: {type(exc).__name__}: {exc}", 500)


def write_error(exc: Exception) -> ServiceError:
    """``disk_full`` (507) for a write that found the disk full, else ``write_failed`` (500), for an
    ``OSError`` or the library's ``OutputError``; the message names the path and the cause."""
    import errno

    full = getattr(exc, "errno", None) in (errno.ENOSPC, errno.EDQUOT)
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if exc.filename else ""
        message = f"cannot write {where}{exc.strerror or exc}"
    else:
        message = str(exc)
    return ServiceError("disk_full" if full else "write_failed", message, 507 if full else 500)
