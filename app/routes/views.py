"""The 3D views: each session's viser client (page and websocket) behind the workbench's port, and its status.

Included only when the app serves 3D views (``create_app(viewers=True)``).
"""

from __future__ import annotations

from typing import Any

import httpx
from fastapi import APIRouter, Request, WebSocket
from fastapi.responses import RedirectResponse, Response
from starlette.concurrency import run_in_threadpool

from app.errors import UnknownSessionError
from app.view.names import AUTHOR_COOKIE, name_from_cookie
from app.view.proxy import forward_file, forward_socket, open_upstream
from app.view.registry import ViewerRegistry

router = APIRouter()


async def _viewer_port(registry: ViewerRegistry, session_id: str) -> int:
    viewer = await run_in_threadpool(registry.get, session_id)  # starting a view reads the session
    return viewer.port


@router.get("/viser/{session_id}", include_in_schema=False)
async def viser_root(session_id: str) -> RedirectResponse:
    return RedirectResponse(f"/viser/{session_id}/")


@router.get("/viser/{session_id}/{path:path}", include_in_schema=False)
async def viser_files(session_id: str, path: str, request: Request) -> Response:
    port = await _viewer_port(request.app.state.viewers, session_id)
    client: httpx.AsyncClient = request.app.state.viser_client
    return await forward_file(client, port, path, request)


@router.websocket("/viser/{session_id}")
async def viser_socket(websocket: WebSocket, session_id: str) -> None:
    """The 3D view's websocket; the browser arrives under the name its page put in the author cookie."""
    registry: ViewerRegistry = websocket.app.state.viewers
    try:
        viewer = await run_in_threadpool(registry.get, session_id)
    except UnknownSessionError:
        await websocket.close(code=4404)
        return
    name = name_from_cookie(websocket.cookies.get(AUTHOR_COOKIE))
    upstream = await viewer.names.admit(name, lambda: open_upstream(websocket, viewer.port))
    if upstream is not None:
        await forward_socket(websocket, upstream)


@router.get("/api/sessions/{session_id}/view", tags=["view"])
def view_status(session_id: str, request: Request) -> dict[str, Any]:
    """State of the session's 3D view (starts it if needed): ready, points shown, revision shown."""
    registry: ViewerRegistry = request.app.state.viewers
    return registry.get(session_id).as_dict()
