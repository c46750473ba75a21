"""A session's head, pushed to its pages as it moves: the websocket ``/api/sessions/{id}/events``.

Guarded like every session read (:mod:`app.guard`: token, role ``viewer``, a session's token on its
own session only, the page's own ``Origin``). A websocket rather than server-sent events because a
stopping server closes websockets at once, whereas an endless HTTP response would hold its shutdown.

Messages (JSON text): first the current head, then one for each change of it - ``{"type":
"revision", "revision", "entry", "author", "kind", "time", "can_undo", "can_redo"}`` (see
:func:`app.revision_events.head_event`) - a ``{"type": "heartbeat"}`` whenever nothing happened for
a while, and ``{"type": "gone"}`` before closing with code 4404 when the session no longer exists.
Refused before opening: an unknown session (4404), too many streams on the session or token (1013,
try again later). The page ignores what it sends; closing is the only message that matters.
"""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import APIRouter, WebSocket
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect

from app.errors import UnknownSessionError
from app.guard import OPEN_GRANT
from app.revision_events import GONE, HEARTBEAT, Listener, RevisionEvents, TooManyListenersError
from slam6d.errors import Slam6dError

router = APIRouter()

GONE_CODE = 4404
FULL_CODE = 1013  # "try again later"


@router.websocket("/api/sessions/{session_id}/events")
async def revision_events(websocket: WebSocket, session_id: str) -> None:
    """The session's head now and at every change (new revision, its author; undo/redo state)."""
    events: RevisionEvents = websocket.app.state.revision_events
    grant = websocket.scope.get("state", {}).get("grant", OPEN_GRANT)
    try:
        first = await run_in_threadpool(events.current, session_id)
        listener = events.subscribe(session_id, grant.id)
    except (UnknownSessionError, Slam6dError):
        await websocket.close(code=GONE_CODE, reason=f"no session '{session_id[:60]}'")
        return
    except TooManyListenersError as exc:
        await websocket.close(code=FULL_CODE, reason=str(exc)[:120])
        return
    try:
        await websocket.accept()
        listener.take(first)
        await websocket.send_json(first)
        await _stream(websocket, events, listener)
    except WebSocketDisconnect:
        pass
    finally:
        events.unsubscribe(listener)


async def _stream(websocket: WebSocket, events: RevisionEvents, listener: Listener) -> None:
    """Send each new head until the page goes (or the session does); a heartbeat when all is quiet."""
    closed = asyncio.ensure_future(_until_closed(websocket))
    try:
        while not closed.done():
            waiting = asyncio.ensure_future(listener.next(events.heartbeat_s))
            await asyncio.wait({closed, waiting}, return_when=asyncio.FIRST_COMPLETED)
            if closed.done():
                waiting.cancel()
                return
            event = waiting.result()
            if event is None:  # quiet: is the session still there, was its head moved by another process?
                try:
                    event = await run_in_threadpool(events.current, listener.session_id)
                except (UnknownSessionError, Slam6dError):
                    await websocket.send_json(GONE)
                    await websocket.close(code=GONE_CODE)
                    return
                await websocket.send_json(listener.take(event) or HEARTBEAT)
            elif listener.take(event) is not None:
                await websocket.send_json(event)
    finally:
        closed.cancel()
        with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect):
            await closed


async def _until_closed(websocket: WebSocket) -> None:
    """Read (and drop) what the page sends until it closes the socket."""
    while (await websocket.receive())["type"] != "websocket.disconnect":
        pass
