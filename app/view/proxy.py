"""Forward a session's viser client page and websocket through the workbench's own port.

The viser client derives its websocket address from the page address (``/viser/{id}/`` connects
to ``ws://host/viser/{id}``) and identifies itself with the ``viser-v<version>`` subprotocol,
which viser needs to accept the connection; both are forwarded unchanged, so the browser never
learns the internal port. The routes are :mod:`app.routes.views`.
"""

from __future__ import annotations

import asyncio
import contextlib

import httpx
import websockets
from fastapi import WebSocket
from fastapi.responses import Response
from starlette.websockets import WebSocketDisconnect
from websockets.asyncio.client import ClientConnection
from websockets.asyncio.client import connect as ws_connect

from app.guard import OPEN_GRANT
from app.view.presence import Presence
from app.view_roles import may_send, message_type

_PASSED_HEADERS = ("content-type", "content-encoding", "cache-control", "etag", "last-modified")


async def forward_file(client: httpx.AsyncClient, port: int, path: str) -> Response:
    """A file of the viser client from the view's internal server: what the workbench does not serve
    itself (:mod:`app.view.client_files` serves the client of a known build without any view).

    Asked for uncompressed: viser gzips a file afresh in every view's server (each session's view
    is one), and its client page (818 KB, mostly already compressed) shrinks by 18 % for ~0.1 s of
    compression at level 9 on the path to the first view, plus the browser's unpacking.
    """
    headers = {"Accept-Encoding": "identity"}
    upstream = await client.send(
        client.build_request("GET", f"http://127.0.0.1:{port}/{path}", headers=headers), stream=True
    )
    try:
        body = b"".join([chunk async for chunk in upstream.aiter_raw()])
    finally:
        await upstream.aclose()
    passed = {k: v for k, v in upstream.headers.items() if k.lower() in _PASSED_HEADERS}
    return Response(body, status_code=upstream.status_code, headers=passed)


async def open_upstream(websocket: WebSocket, port: int) -> ClientConnection | None:
    """The view's internal websocket for this browser, with the subprotocol it offered; None (and the
    browser's socket closed) when the view does not answer."""
    offered = [p for p in websocket.scope.get("subprotocols", []) if p.startswith("viser-v")]
    try:
        return await ws_connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[websockets.Subprotocol(p) for p in offered] or None,
            max_size=None,
            compression=None,
            open_timeout=10,
            ping_interval=None,
        )
    except (OSError, websockets.InvalidHandshake, TimeoutError):
        await websocket.close(code=1011)
        return None


ANNOUNCE_TIMEOUT = 5.0  # seconds a browser's first camera may take to register it with viser
_announcing: dict[int, asyncio.Lock] = {}  # per presence: one browser announced at a time


async def forward_socket(
    websocket: WebSocket,
    upstream: ClientConnection,
    presence: Presence | None = None,
    key: str | None = None,
    private: bool = False,
) -> None:
    """Accept the browser's websocket and join it to the view's internal one until either side closes.

    What a browser below editor sends is filtered (:mod:`app.view_roles`; ``private``: a view of its own). With ``presence`` and a view
    ``key`` (the session page's own 3D view), the browser's first camera message - the one that makes
    viser register it - goes through :meth:`Presence.announce`, so the view knows that client's key,
    name and role.
    """
    await websocket.accept(subprotocol=upstream.subprotocol)
    grant = websocket.scope.get("state", {}).get("grant", OPEN_GRANT)
    unannounced = presence is not None and key is not None

    async def announce_with(payload: bytes) -> None:
        assert presence is not None and key is not None
        async with _announcing.setdefault(id(presence), asyncio.Lock()):
            done = presence.announce(key, grant)
            await upstream.send(payload)
            if not await asyncio.to_thread(done.wait, ANNOUNCE_TIMEOUT):
                presence.withdraw(done)

    async def to_browser() -> None:
        async for message in upstream:
            if isinstance(message, bytes):
                await websocket.send_bytes(message)
            else:
                await websocket.send_text(message)

    async def to_viser() -> None:
        nonlocal unannounced
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            payload = message.get("bytes") if message.get("bytes") is not None else message.get("text")
            if payload is None or not may_send(grant, payload, private):  # a viewer's clicks and drags stop here
                continue
            if unannounced and isinstance(payload, bytes) and message_type(payload) == "ViewerCameraMessage":
                unannounced = False
                await announce_with(payload)
            else:
                await upstream.send(payload)

    tasks = [asyncio.create_task(to_browser()), asyncio.create_task(to_viser())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, websockets.ConnectionClosed):
                await task
        await upstream.close()
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await websocket.close()
