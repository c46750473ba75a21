"""Request bodies are bounded per endpoint and JSON strings must be valid UTF-8, before any route runs.

An ASGI middleware, because the checks must happen before FastAPI reads a body: a 30 MB JSON body
is refused with 413 from its ``Content-Length`` (or, without one, as soon as the counted bytes pass
the limit) instead of being parsed into half a gigabyte of Python objects. Uploads stream through
counted (the route spools them to disk); every other body is at most ``json_limit`` and is read
here, checked and handed on. A JSON string holding a lone surrogate (``"\\ud800"``, valid JSON
but not encodable text) is refused with 422 naming where it is; it would otherwise fail later
inside SQLite or the answer's encoder as a 500.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from app.errors import WorkbenchError

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

JSON_LIMIT_BYTES = 2 << 20  # 10,000 keyframes of a camera path fit with room to spare


class RequestTooLargeError(WorkbenchError):
    default_status = 413


class RequestLimits:
    """Bounds request bodies: ``upload_limit`` for paths ending in one of ``upload_paths``, else ``json_limit``."""

    def __init__(
        self, app: ASGIApp, upload_limit: int, upload_paths: tuple[str, ...], json_limit: int = JSON_LIMIT_BYTES
    ) -> None:
        self.app = app
        self.upload_limit = upload_limit
        self.upload_paths = upload_paths
        self.json_limit = json_limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        streamed = scope["path"].endswith(self.upload_paths)
        limit = self.upload_limit if streamed else self.json_limit
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > limit:
            await _answer(send, 413, _too_large(limit))
            return
        if streamed:
            await self.app(scope, _counted(receive, limit), send)
            return
        body, more = b"", True
        while more:
            message = await receive()
            if message["type"] != "http.request":
                break
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > limit:
                await _answer(send, 413, _too_large(limit))
                return
        if body and "json" in headers.get("content-type", ""):
            problem = _json_text_problem(body)
            if problem is not None:
                await _answer(send, 422, [{"loc": ["body", *problem[0]], "msg": problem[1], "type": "string_unicode"}])
                return
        await self.app(scope, _replay(body, receive), send)


def _too_large(limit: int) -> str:
    return f"request body exceeds this endpoint's limit of {limit:,} bytes"


def _counted(receive: Receive, limit: int) -> Receive:
    seen = 0

    async def counted() -> Message:
        nonlocal seen
        message = await receive()
        seen += len(message.get("body", b""))
        if seen > limit:
            raise RequestTooLargeError(_too_large(limit))
        return message

    return counted


def _replay(body: bytes, receive: Receive) -> Receive:
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


def _json_text_problem(body: bytes) -> tuple[list[str | int], str] | None:
    """Where (and what) makes a JSON body's text invalid, or None (malformed JSON is FastAPI's to answer)."""
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        return [], "body is not valid UTF-8"
    try:
        value = json.loads(text)
    except ValueError:
        return None
    return _lone_surrogate(value, [])


def _lone_surrogate(value: Any, where: list[str | int]) -> tuple[list[str | int], str] | None:
    if isinstance(value, str):
        if any("\ud800" <= c <= "\udfff" for c in value):
            return where, "string is not valid UTF-8 (it holds a lone surrogate escape such as \\ud800)"
        return None
    items: Any = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        if isinstance(key, str) and any("\ud800" <= c <= "\udfff" for c in key):
            return [*where, "(key)"], "object key is not valid UTF-8 (lone surrogate)"
        found = _lone_surrogate(item, [*where, key])
        if found is not None:
            return found
    return None


async def _answer(send: Send, status: int, detail: Any) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
        }
    )
    await send({"type": "http.response.body", "body": body})
