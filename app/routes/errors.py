"""The one place where an error becomes an HTTP status.

Routes raise (or let through) typed errors and never build ``HTTPException`` for them: an unknown
session is 404, a workbench refusal carries its own status (:class:`app.errors.WorkbenchError`), a
relaxation that cannot run is a conflict with the graph (409), and any other engine error is the
user's data or settings at fault (422). The body is FastAPI's usual ``{"detail": message}``.
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from app.errors import UnknownSessionError, WorkbenchError
from slam6d.errors import RelaxationError, Slam6dError


def status_of(exc: Exception) -> int:
    """The HTTP status of an error the workbench knows; 500 for anything else."""
    if isinstance(exc, UnknownSessionError):
        return 404
    if isinstance(exc, WorkbenchError):
        return exc.status
    if isinstance(exc, RelaxationError):
        return 409
    if isinstance(exc, Slam6dError):
        return 422
    return 500


async def _answer(_: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=status_of(exc))


def install_error_handlers(app: FastAPI) -> None:
    for error in (UnknownSessionError, Slam6dError):  # subclasses of Slam6dError resolve in status_of
        app.add_exception_handler(error, _answer)
