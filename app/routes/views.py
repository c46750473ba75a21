"""The 3D views: each session's viser client (page and websocket) behind the workbench's port, and its status.

A session has one live 3D view (the head, shared by everyone on it) and private read-only views
(:mod:`app.view.revision_view`, a scene per browser): of an older revision while a permalink to it
is open, and of the head for browsers in colours of their own. Presence, camera, colour mode and
selection routes find a browser by its view key in any of them.

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
from app.view.client_files import CLIENT_PREFIX, installed_client
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
    """The 3D view's client page. Split into cacheable files (:mod:`app.view.client_files`) it needs no
    view to answer: the view is started meanwhile, and the page's websocket waits for it."""
    client = await run_in_threadpool(installed_client)  # (decoded as the server started: at once)
    if path == "" and client.split:
        registry: ViewerRegistry = request.app.state.viewers
        await run_in_threadpool(registry.start, session_id)
        return client.page_response()
    port = await _viewer_port(request.app.state.viewers, session_id)
    forwarder: httpx.AsyncClient = request.app.state.viser_client
    return await forward_file(forwarder, port, path)


@router.get(
    CLIENT_PREFIX + "/{digest}/{name}", include_in_schema=False, openapi_extra=requires(Role.viewer, any_session=True)
)
async def viser_client_file(digest: str, name: str, request: Request) -> Response:
    """A file of the 3D client (script, styles, decoder): immutable under its build's digest, gzip when accepted.
    The same for every session, so a token made for one session fetches it too."""
    client = await run_in_threadpool(installed_client)
    found = client.files.get(name)
    if found is None or digest != client.digest:
        return Response(f"no client file {digest}/{name} in this server's viser build", status_code=404)
    return found.response(request)


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
    await _private_socket(websocket, session_id, revision, view_key[:64])


@router.websocket("/viser/{session_id}/head/as/{view_key}")
async def viser_socket_head(websocket: WebSocket, session_id: str, view_key: str) -> None:
    """The head in the browser's own colours (a viewer or reviewer whose colour mode is not the live
    view's): read-only, following every new revision."""
    await _private_socket(websocket, session_id, None, view_key[:64])


async def _private_socket(websocket: WebSocket, session_id: str, revision: int | None, view_key: str) -> None:
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
    state["grant"] = replace(grant, role=min(grant.role, Role.viewer))  # its camera and clicks reach the view
    upstream = await open_upstream(websocket, view.port)
    if upstream is not None:
        await forward_socket(websocket, upstream, presence_of(view), view_key, private=True)


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
def view_status(session_id: str, request: Request, rev: RevisionQuery = None, own: bool = False) -> dict[str, Any]:
    """State of the session's 3D view (starts it if needed): ready, points shown, revision shown, colour.

    With ``rev`` naming an older revision: that revision's read-only view (what a permalink to it
    draws), with each scan's position there; with ``own=true``: the view of the head in browsers' own
    colours, with each browser's colour mode. 409 when the server has no room for another such view."""
    registry: ViewerRegistry = request.app.state.viewers
    live = registry.get(session_id)
    views: RevisionViews = request.app.state.revision_views
    if own:
        return views.get(session_id, None).as_dict()
    if rev is None or rev == live.state.session.revision:
        return live.as_dict()
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
    """The session's 3D views: the live one (revision None: the head), the head in browsers' own colours
    (None too) and its open older revisions."""
    registry: ViewerRegistry = request.app.state.viewers
    views: RevisionViews = request.app.state.revision_views
    private = ((None if v.follows_head else v.revision, v) for v in views.of_session(session_id))
    return [(None, registry.get(session_id)), *private]


def _kind(view: Any) -> str:
    """Which of the session's views: ``live`` (shared), ``own`` (the head in own colours) or ``old``."""
    if not isinstance(view, RevisionView):
        return "live"
    return "own" if view.follows_head else "old"


def _picked(person: Person) -> dict[str, Any]:
    """What the browser last picked in the 3D view itself, and how many picks it made there (the page polls it)."""
    marker = marker_of(person.client)
    return {"picks": marker.picks, "picked": None if marker.last_pick is None else marker.last_pick.text()}


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
    ``revision`` (null: the head; a number: an older revision opened from a permalink), ``view`` (``live``,
    ``own`` - the head in their own colours - or ``old``) and what they last picked in the 3D view
    (``picked``, as a link's ``sel``; ``picks`` counts those picks)."""
    listed = []
    for revision, view in _views(request, session_id):
        presence = presence_of(view)
        for entry in presence.listed():
            person = presence.person(entry["key"])
            picks = {"picks": 0, "picked": None} if person is None else _picked(person)
            listed.append({**entry, "revision": revision, "view": _kind(view), **picks})
    return listed


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
    """Your 3D view's colour mode. On a private view (an older revision, or the head in your own colours) it
    is yours alone; the live view's colouring is one setting shared by everyone on it (its "Colour by"
    control), so only an editor changes it there - the page moves anyone else to the head in their own
    colours (``/viser/{id}/head/as/{key}``)."""
    view, _presence, person = _own(request, session_id, key)
    if isinstance(view, RevisionView):
        view.set_colour(person.client.client_id, body.mode)
        return {"key": key, "colour": body.mode, "shared": False}
    grant = getattr(request.state, "grant", OPEN_GRANT)
    if grant.role < Role.editor:
        raise EditError(
            "the shared 3D view's colouring is everyone's on it: only an editor changes it; "
            "your own colours are drawn in a view of your own (the page opens it)",
            403,
        )
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
