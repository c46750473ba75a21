"""The one place where an error becomes an HTTP status, and the one shape every error answer has.

Routes raise (or let through) typed errors and never build ``HTTPException`` for them: an unknown
session is 404, a workbench refusal carries its own status (:class:`app.errors.WorkbenchError`), a
relaxation that cannot run is a conflict with the graph (409), and any other engine error is the
user's data or settings at fault (422). A request that does not match its schema is 422 with
FastAPI's list of problems (location, message, type) - without echoing the refused input, which
may be what cannot be encoded. Anything else is a bug: it is logged with a fresh id and answered
500 with that id only, never a traceback or a message that could carry a file's content.

Every answer is ``{"detail": ...}``: a message (str) for refusals, a list for schema problems;
:class:`ErrorBody` documents exactly that for every route in the OpenAPI schema.
"""

from __future__ import annotations

import logging
import uuid
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.errors import UnknownSessionError, WorkbenchError
from slam6d.archive import ArchiveError
from slam6d.errors import RelaxationError, Slam6dError

log = logging.getLogger("slam6d.workbench")


class ValidationIssue(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class ErrorBody(BaseModel):
    """What every refusal answers: a message, or (422 from schema validation) the list of problems."""

    detail: str | list[ValidationIssue]


def status_of(exc: Exception) -> int:
    """The HTTP status of an error the workbench knows; 500 for anything else."""
    if isinstance(exc, UnknownSessionError):
        return 404
    if isinstance(exc, WorkbenchError):
        return exc.status
    if isinstance(exc, RelaxationError):
        return 409
    if isinstance(exc, ArchiveError) and exc.too_large:
        return 413
    if isinstance(exc, Slam6dError):
        return 422
    return 500


def issues(errors: Any) -> list[dict[str, Any]]:
    """Schema problems as plain JSON: location, message, type - the refused input is left out."""
    out = []
    for error in errors:
        loc = [p if isinstance(p, int) else _printable(str(p)) for p in error.get("loc", ())]
        out.append({"loc": loc, "msg": _printable(str(error.get("msg", ""))), "type": str(error.get("type", ""))})
    return out


def _printable(text: str) -> str:
    """Text that encodes as UTF-8 (a lone surrogate from a JSON escape would break the answer)."""
    return text.encode("utf-8", "replace").decode("utf-8")


async def _refused(_: Request, exc: Exception) -> JSONResponse:
    status = status_of(exc)
    if status == 500:
        return await _unexpected(_, exc)
    return JSONResponse({"detail": _printable(str(exc))}, status_code=status)


async def _invalid(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return JSONResponse({"detail": issues(exc.errors())}, status_code=422)


async def _http(request: Request, exc: Exception) -> JSONResponse:
    """Starlette's own refusals keep their status, except a body it could not parse (400): that is an
    invalid request like any other, 422."""
    assert isinstance(exc, StarletteHTTPException)
    status = 422 if exc.status_code == 400 else exc.status_code
    return JSONResponse({"detail": _printable(str(exc.detail))}, status_code=status, headers=exc.headers)


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    reference = uuid.uuid4().hex[:12]
    log.error("unexpected error %s on %s %s", reference, request.method, request.url.path, exc_info=exc)
    return JSONResponse({"detail": f"internal error (reference {reference}); the server log has the details"}, 500)


_REASONS = {
    404: "No such session, job, scan, edge, loop, keyframe or revision.",
    409: "Conflicts with the session's state (nothing to undo, the session's job queue full, a graph that cannot relax).",
    413: "The request body (or what an archive in it expands to) exceeds this endpoint's limit.",
    422: "Invalid request (schema problems as a list) or data the engine refuses (a message naming file or field).",
    500: "A bug: the answer holds only a reference to the server log.",
}


def error_statuses(path: str, method: str, has_body: bool) -> list[int]:
    """The error statuses an operation can answer, from what it takes: a path parameter can name
    something absent (404), anything on a session or job can conflict with its state (409), a body
    can be too large (413), and anything can be invalid (422) or hit a bug (500)."""
    statuses = [422, 500]
    if "{" in path:
        statuses.append(404)
    if "{session_id}" in path or "{job_id}" in path:
        statuses.append(409)
    if has_body:
        statuses.append(413)
    return sorted(statuses)


def document_errors(app: FastAPI) -> None:
    """Make ``/openapi.json`` say what the API answers: every error status an operation can give, each
    with :class:`ErrorBody` (replacing FastAPI's 422 schema, which only knew the list form)."""
    original = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = original()
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        components["ValidationIssue"] = ValidationIssue.model_json_schema()
        body = ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}")
        body.pop("$defs", None)
        components["ErrorBody"] = body
        for path, operations in schema.get("paths", {}).items():
            for method, operation in operations.items():
                responses = operation.setdefault("responses", {})
                for status in error_statuses(path, method, "requestBody" in operation):
                    responses[str(status)] = {
                        "description": _REASONS[status],
                        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}},
                    }
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def install_error_handlers(app: FastAPI) -> None:
    for error in (UnknownSessionError, Slam6dError):  # subclasses of Slam6dError resolve in status_of
        app.add_exception_handler(error, _refused)
    app.add_exception_handler(RequestValidationError, _invalid)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(Exception, _unexpected)
