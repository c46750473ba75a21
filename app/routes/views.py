"""The 3D views: each session's viser client (page and websocket) behind the workbench's port, and its status.

Included only when the app serves 3D views (``create_app(viewers=True)``).
"""

from __future__ import annotations

from typing import Annotated, Any

import httpx
from fastapi import APIRouter, Request, WebSocket
from fastapi.responses import RedirectResponse, Response
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from app.errors import EditError, UnknownSessionError
from app.guard import OPEN_GRANT, requires
from app.tokens import Role
from app.view.names import AUTHOR_COOKIE, name_from_cookie
from app.view.presence import Person, Presence, presence_of
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
    await _socket(websocket, session_id, None)


@router.websocket("/viser/{session_id}/as/{view_key}")
async def viser_socket_as(websocket: WebSocket, session_id: str, view_key: str) -> None:
    """The session page's own 3D view: ``view_key`` names it for presence, follow and permalinks."""
    await _socket(websocket, session_id, view_key[:64])


async def _socket(websocket: WebSocket, session_id: str, view_key: str | None) -> None:
    registry: ViewerRegistry = websocket.app.state.viewers
    try:
        viewer = await run_in_threadpool(registry.get, session_id)
    except UnknownSessionError:
        await websocket.close(code=4404)
        return
    grant = websocket.scope.get("state", {}).get("grant", OPEN_GRANT)
    # a token's holder arrives under the token's name, whatever the page's name field says
    name = grant.name if grant is not OPEN_GRANT else name_from_cookie(websocket.cookies.get(AUTHOR_COOKIE))
    upstream = await viewer.names.admit(name, lambda: open_upstream(websocket, viewer.port))
    if upstream is not None:
        await forward_socket(websocket, upstream, presence_of(viewer), view_key)


@router.get("/api/sessions/{session_id}/view", tags=["view"])
def view_status(session_id: str, request: Request) -> dict[str, Any]:
    """State of the session's 3D view (starts it if needed): ready, points shown, revision shown."""
    registry: ViewerRegistry = request.app.state.viewers
    return registry.get(session_id).as_dict()


class CameraBody(BaseModel):
    """A view in the canonical frame (metres, z up)."""

    position: list[Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)]] = Field(min_length=3, max_length=3)
    look_at: list[Annotated[float, Field(allow_inf_nan=False, ge=-1e6, le=1e6)]] = Field(min_length=3, max_length=3)
    up: list[Annotated[float, Field(allow_inf_nan=False, ge=-1.0, le=1.0)]] = Field(
        default_factory=lambda: [0.0, 0.0, 1.0], min_length=3, max_length=3
    )
    fov_deg: float = Field(60.0, ge=1.0, lt=179.0)


class FollowBody(BaseModel):
    target: str | None = Field(None, max_length=64, description="the view key to follow; null stops following")


def _presence(request: Request, session_id: str) -> Presence:
    registry: ViewerRegistry = request.app.state.viewers
    return presence_of(registry.get(session_id))


def _own(request: Request, presence: Presence, key: str) -> Person:
    """The browser ``key``, if the request comes from its holder (the same token; anyone on an open server)."""
    person = presence.person(key)
    if person is None:
        raise EditError(f"no browser '{key}' on this session's 3D view", 404)
    grant = getattr(request.state, "grant", OPEN_GRANT)
    if grant is not OPEN_GRANT and grant.id != person.grant.id:
        raise EditError("that 3D view belongs to someone else", 403)
    return person


@router.get("/api/sessions/{session_id}/presence", tags=["view"])
def presence(session_id: str, request: Request) -> list[dict[str, Any]]:
    """Who has the session's 3D view open: view key, name, role, seconds idle, whom they follow, camera."""
    return _presence(request, session_id).listed()


@router.get("/api/sessions/{session_id}/presence/{key}/camera", tags=["view"])
def view_camera(session_id: str, key: str, request: Request) -> dict[str, Any]:
    """One browser's camera (canonical frame): what a permalink stores."""
    person = _presence(request, session_id).person(key)
    if person is None:
        raise EditError(f"no browser '{key}' on this session's 3D view", 404)
    return person.camera()


@router.post("/api/sessions/{session_id}/presence/{key}/camera", tags=["view"], openapi_extra=requires(Role.viewer))
def place_camera(session_id: str, key: str, body: CameraBody, request: Request) -> dict[str, Any]:
    """Move your own 3D view's camera (opening a permalink); changes nobody else's view."""
    presence = _presence(request, session_id)
    _own(request, presence, key)
    presence.place(key, body.model_dump())
    return {"key": key, "camera": body.model_dump()}


@router.post("/api/sessions/{session_id}/presence/{key}/follow", tags=["view"], openapi_extra=requires(Role.viewer))
def follow(session_id: str, key: str, body: FollowBody, request: Request) -> dict[str, Any]:
    """Your 3D view takes another browser's view whenever it moves (``target`` null: stop)."""
    presence = _presence(request, session_id)
    _own(request, presence, key)
    try:
        presence.follow(key, body.target)
    except LookupError as exc:
        raise EditError(str(exc), 404) from None
    except ValueError as exc:
        raise EditError(str(exc), 409) from None
    return {"key": key, "follows": body.target}
