"""Revisions over HTTP: every session response says its revision, a stale ``If-Match`` changes nothing.

Every response about a session carries ``ETag: "<revision>"`` (the session's head when the
response was made). A state-changing request may send that value back in ``If-Match``: if the
session has moved on meanwhile, it is answered 412 with the revisions since and who made them,
and nothing is applied - checked once here, and again inside the journal's write transaction
(:func:`slam6d.journal.expecting`), so an edit racing in between cannot slip through. Clients
that do not send ``If-Match`` get the journal's default: their change is applied to the head.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.requests import HTTPConnection
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from slam6d.journal import EditConflictError, Journal, JournalEntry, StaleRevisionError, expect_head

READ_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


class RevisionEntry(BaseModel):
    revision: int | None
    kind: str
    author: str
    time: str


class StaleRevision(BaseModel):
    """A 412: the session's head and what changed it since the revision the request named."""

    detail: str
    head: int | None
    since: list[RevisionEntry]


REVISION_RESPONSES: dict[int | str, dict[str, Any]] = {
    412: {
        "model": StaleRevision,
        "description": "If-Match names a revision that is no longer the head; nothing applied",
    },
}


def entry_summary(entry: JournalEntry) -> dict[str, Any]:
    return {"revision": entry.head, "kind": entry.kind, "author": entry.author, "time": entry.time}


def stale_body(error: StaleRevisionError) -> dict[str, Any]:
    return {"detail": str(error), "head": error.head, "since": [entry_summary(e) for e in error.since]}


def conflict_body(error: EditConflictError) -> dict[str, Any]:
    return {
        "detail": str(error),
        "base": error.base,
        "scans": error.scans,
        "edit": None if error.entry is None else entry_summary(error.entry),
    }


def check_revision(journal_of: Callable[[str], Journal | None]) -> Callable[[HTTPConnection], Awaitable[None]]:
    """The dependency that refuses a stale ``If-Match`` (412) and has the journal check it again on write.

    It runs after :func:`app.guard.authorize`, which found the session the request acts on.
    """

    async def check(connection: HTTPConnection) -> None:
        if connection.scope["type"] != "http" or str(connection.scope["method"]).upper() in READ_METHODS:
            return
        raw = connection.headers.get("if-match")
        session = getattr(connection.state, "session", None)
        journal = None if session is None or raw is None or raw.strip() == "*" else journal_of(session)
        if journal is None:
            return
        expected = parse_revision_tag(raw or "")
        if expected is None:
            raise HTTPException(400, f'If-Match must be a revision in quotes, e.g. "3" (got {(raw or "")[:40]!r})')
        head = journal.head
        if head != expected and not (head is None and expected == 0):  # as the journal: 0 before it is stored
            raise StaleRevisionError(journal.path.parent, expected, head, journal.since(expected))
        expect_head(expected)

    return check


class RevisionHeaders:
    """ASGI middleware: ``ETag: "<revision>"`` on every response about a session, and the request's
    ``If-Match`` (accepted by :func:`check_revision`) held over the journal writes the request makes."""

    def __init__(self, app: ASGIApp, journal_of: Callable[[str], Journal | None]) -> None:
        self.app = app
        self.journal_of = journal_of

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        state = scope.setdefault("state", {})

        async def send_with_etag(message: Message) -> None:
            session = state.get("session")
            journal = None if message["type"] != "http.response.start" or session is None else self.journal_of(session)
            if journal is not None:
                head = journal.head or 0  # a session shows revision 0 (its files' poses) before storing it
                headers = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"etag"]
                message = {**message, "headers": [*headers, (b"etag", f'"{head}"'.encode())]}
            await send(message)

        await self.app(scope, receive, send_with_etag)


def parse_revision_tag(raw: str) -> int | None:
    """``"3"``, ``W/"3"`` or ``3`` -> 3; anything else None."""
    text = raw.strip()
    if text.startswith("W/"):
        text = text[2:]
    text = text.strip('"')
    return int(text) if text.isdigit() and len(text) < 18 else None


def add_revision_errors(app: FastAPI) -> None:
    """412 for a write refused inside the journal's transaction, 409 for a job's conflicting edit."""

    async def stale(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StaleRevisionError)
        return JSONResponse(stale_body(exc), status_code=412)

    async def conflict(_request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, EditConflictError)
        return JSONResponse(conflict_body(exc), status_code=409)

    app.add_exception_handler(StaleRevisionError, stale)
    app.add_exception_handler(EditConflictError, conflict)


__all__ = ["REVISION_RESPONSES", "RevisionHeaders", "add_revision_errors", "check_revision", "parse_revision_tag"]
