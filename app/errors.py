"""What the workbench refuses, each with the HTTP status that fits; :mod:`app.routes.errors` maps them.

Engine errors (:class:`~slam6d.errors.Slam6dError`) are the user's data or settings at fault (422),
a relaxation that cannot run is a conflict with the graph (409); the workbench's own refusals carry
their status, so a button in the 3D view and a REST call report the same thing.
"""

from __future__ import annotations

from slam6d.errors import Slam6dError


class WorkbenchError(Slam6dError):
    """A request the workbench refuses; ``status`` is the HTTP status that fits."""

    default_status = 422

    def __init__(self, message: str, status: int | None = None) -> None:
        self.status = self.default_status if status is None else status
        super().__init__(message)


class EditError(WorkbenchError):
    """An edit cannot be made (404 an unknown scan, edge or loop; 409 a conflict with the state; 422 bad values)."""

    default_status = 409


class UploadError(WorkbenchError):
    """An upload was refused (413 too large, 422 invalid)."""


class PartialResultError(Slam6dError):
    """A job failed part-way but kept what it had done (e.g. a registration's poses as a revision);
    ``result`` is what it kept, reported with the failure."""

    def __init__(self, message: str, result: dict[str, object]) -> None:
        self.result = result
        super().__init__(message)


class JobConflictError(WorkbenchError):
    """The session already has as many jobs queued as it may hold."""

    default_status = 409


class ParseTimeoutError(WorkbenchError):
    """Reading scans took longer than the server's parse time limit (the message names the file)."""

    default_status = 422


class UnknownSessionError(LookupError):
    """No session folder of that id: 404, never a hint of what else exists on the server."""

    def __init__(self, session_id: str) -> None:
        self.session_id = session_id
        super().__init__(f"no session '{session_id}'")


__all__ = ["EditError", "JobConflictError", "ParseTimeoutError", "UnknownSessionError", "UploadError", "WorkbenchError"]
