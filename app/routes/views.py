"""The 3D views: each session's viser client (page and websocket) behind the workbench's port, and its status.

A session has one live 3D view (the head, shared by everyone on it) and, while a permalink to an
older revision is open, a read-only view of that revision (:mod:`app.view.revision_view`). Presence,
camera, colour mode and selection routes find a browser by its view key in either.

Included only when the app serves 3D views (``create_app(viewers=True)``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Annotated, Any, Literal

import httpx
from fastapi import APIRouter, Request, WebSocket
from fastapi.responses import RedirectResponse, Response
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from app.editing import editor_for
from app.errors import EditError, UnknownSessionError
from app.guard import OPEN_GRANT, requires
from app.permalink import describe_selection, parse_selection
from app.tokens import Role
from app.validation import RevisionQuery
from app.view.presence import Person, Presence, presence_of
from app.view.proxy import forward_file, forward_socket, open_upstream
from app.view.registry import ViewerRegistry
from app.view.revision_view import RevisionView, RevisionViews
from app.view.selection_marker import marker_of
from slam6d.errors import Slam6dError

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
    return await forward_file(client, port, path)


@router.websocket("/viser/{session_id}")
async def viser_socket(websocket: WebSocket, session_id: str) -> None:
    """The 3D view's websocket; the browser arrives under the name its page put in the author cookie."""
    await _socket(websocket, session_id, None)


@router.websocket("/viser/{session_id}/as/{view_key}")
async def viser_socket_as(websocket: WebSocket, session_id: str, view_key: str) -> None:
    """The session page's own 3D view: ``view_key`` names it for presence, follow and permalinks."""
    await _socket(websocket, session_id, view_key[:64])


@router.websocket("/viser/{session_id}/at/{revision}/as/{view_key}")
async def viser_socket_at(websocket: WebSocket, session_id: str, revision: int, view_key: str) -> None:
    """An older revision's 3D view (a permalink to it): read-only, whatever the browser's role."""
    views: RevisionViews = websocket.app.state.revision_views
    try:
        view = await run_in_threadpool(views.get, session_id, revision)
    except UnknownSessionError:
        await websocket.close(code=4404)
        return
    except Slam6dError:  # no such revision, too many open
        await websocket.close(code=4409)
        return
    state = websocket.scope.setdefault("state", {})
    grant = state.get("grant", OPEN_GRANT)
    state["grant"] = replace(grant, role=min(grant.role, Role.viewer))  # only its camera reaches the view
    upstream = await open_upstream(websocket, view.port)
    if upstream is not None:
        await forward_socket(websocket, upstream, presence_of(view), view_key[:64])


async def _socket(websocket: WebSocket, session_id: str, view_key: str | None) -> None:
    registry: ViewerRegistry = websocket.app.state.viewers
    try:
        viewer = await run_in_threadpool(registry.get, session_id)
    except UnknownSessionError:
        await websocket.close(code=4404)
        return
    grant = websocket.scope.get("state", {}).get("grant", OPEN_GRANT)
    # the grant's one name (a token's, or the page's name field on an open server): journal and presence
    upstream = await viewer.names.admit(grant.name, lambda: open_upstream(websocket, viewer.port))
    if upstream is not None:
        await forward_socket(websocket, upstream, presence_of(viewer), view_key)


@router.get("/api/sessions/{session_id}/view", tags=["view"])
def view_status(session_id: str, request: Request, rev: RevisionQuery = None) -> dict[str, Any]:
    """State of the session's 3D view (starts it if needed): ready, points shown, revision shown, colour.

    With ``rev`` naming an older revision: that revision's read-only view (what a permalink to it
    draws), with each scan's position there."""
    registry: ViewerRegistry = request.app.state.viewers
    live = registry.get(session_id)
    if rev is None or rev == live.state.session.revision:
        return live.as_dict()
    views: RevisionViews = request.app.state.revision_views
    return views.get(session_id, rev).as_dict()


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


class ColourBody(BaseModel):
    mode: Literal["scan", "height", "residual", "component"]


class SelectionBody(BaseModel):
    sel: str | None = Field(None, max_length=40, description="scan:K, edge:I-J or loop:I-J; null clears")


def _views(request: Request, session_id: str) -> list[tuple[int | None, Any]]:
    """The session's 3D views: the live one (revision None: the head) and its open older revisions."""
    registry: ViewerRegistry = request.app.state.viewers
    views: RevisionViews = request.app.state.revision_views
    return [(None, registry.get(session_id)), *((v.revision, v) for v in views.of_session(session_id))]


def _presence(request: Request, session_id: str) -> Presence:
    registry: ViewerRegistry = request.app.state.viewers
    return presence_of(registry.get(session_id))


def _find(request: Request, session_id: str, key: str) -> tuple[Any, Presence, Person]:
    """The view the browser ``key`` is on (live or an older revision's), its presence and the browser."""
    for _revision, view in _views(request, session_id):
        presence = presence_of(view)
        person = presence.person(key)
        if person is not None:
            return view, presence, person
    raise EditError(f"no browser '{key}' on this session's 3D views", 404)


def _own(request: Request, session_id: str, key: str) -> tuple[Any, Presence, Person]:
    """The browser ``key``, if the request comes from its holder (the same token; anyone on an open server)."""
    view, presence, person = _find(request, session_id, key)
    grant = getattr(request.state, "grant", OPEN_GRANT)
    if grant.id != person.grant.id:
        raise EditError("that 3D view belongs to someone else", 403)
    return view, presence, person


@router.get("/api/sessions/{session_id}/presence", tags=["view"])
def presence(session_id: str, request: Request) -> list[dict[str, Any]]:
    """Who has the session's 3D views open: view key, name, role, seconds idle, whom they follow, camera,
    and ``revision`` (null: the live head; a number: an older revision opened from a permalink)."""
    return [
        {**person, "revision": revision}
        for revision, view in _views(request, session_id)
        for person in presence_of(view).listed()
    ]


@router.get("/api/sessions/{session_id}/presence/{key}/camera", tags=["view"])
def view_camera(session_id: str, key: str, request: Request) -> dict[str, Any]:
    """One browser's camera (canonical frame): what a permalink stores."""
    return _find(request, session_id, key)[2].camera()


@router.post("/api/sessions/{session_id}/presence/{key}/camera", tags=["view"], openapi_extra=requires(Role.viewer))
def place_camera(session_id: str, key: str, body: CameraBody, request: Request) -> dict[str, Any]:
    """Move your own 3D view's camera (opening a permalink); changes nobody else's view."""
    _view, presence, _person = _own(request, session_id, key)
    presence.place(key, body.model_dump())
    return {"key": key, "camera": body.model_dump()}


@router.post("/api/sessions/{session_id}/presence/{key}/colour", tags=["view"], openapi_extra=requires(Role.viewer))
def set_colour(session_id: str, key: str, body: ColourBody, request: Request) -> dict[str, Any]:
    """Your 3D view's colour mode. On an older revision's view it is yours alone; the live view's colouring
    is one setting shared by everyone on it (its "Colour by" control), so only an editor changes it."""
    view, _presence, person = _own(request, session_id, key)
    if isinstance(view, RevisionView):
        view.set_colour(person.client.client_id, body.mode)
        return {"key": key, "colour": body.mode, "shared": False}
    grant = getattr(request.state, "grant", OPEN_GRANT)
    if grant.role < Role.editor:
        raise EditError("the live 3D view's colouring is shared by everyone on it: only an editor changes it", 403)
    view.controls.colour.value = body.mode  # as the control itself: everyone's view is recoloured
    return {"key": key, "colour": body.mode, "shared": True}


@router.post("/api/sessions/{session_id}/presence/{key}/selection", tags=["view"], openapi_extra=requires(Role.viewer))
def select(session_id: str, key: str, body: SelectionBody, request: Request) -> dict[str, Any]:
    """Mark a scan, edge or loop hypothesis in your own 3D view (nobody else's) and describe it as it is at
    the revision that view shows; 422 naming ``sel`` when it is malformed or not there."""
    view, _presence, person = _own(request, session_id, key)
    selection = parse_selection(body.sel)
    state = request.app.state.workbench.state(session_id)
    if isinstance(view, RevisionView):
        revision, poses = view.revision, view.poses

        def bounds(k: int) -> tuple[Any, Any]:
            return view.bounds[k]
    else:
        revision, poses = state.session.revision, state.session.poses()

        def bounds(k: int) -> tuple[Any, Any]:
            points = state.sequence().scans[k].points
            return points.min(axis=0), points.max(axis=0)

    editor = editor_for(request.app.state.workbench)
    described = None if selection is None else describe_selection(state, editor, selection, revision)
    marker_of(person.client).show(selection, poses, bounds)
    return {"key": key, "revision": revision, "selection": described}


@router.post("/api/sessions/{session_id}/presence/{key}/follow", tags=["view"], openapi_extra=requires(Role.viewer))
def follow(session_id: str, key: str, body: FollowBody, request: Request) -> dict[str, Any]:
    """Your 3D view takes another browser's view whenever it moves (``target`` null: stop)."""
    _view, presence, _person = _own(request, session_id, key)
    try:
        presence.follow(key, body.target)
    except LookupError as exc:
        raise EditError(str(exc), 404) from None
    except ValueError as exc:
        raise EditError(str(exc), 409) from None
    return {"key": key, "follows": body.target}
