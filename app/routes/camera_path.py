"""REST for fly-throughs: the session's camera path (keyframes), render jobs, and the finished videos.

Every keyframe edit is saved at once and shown in every 3D view of the session; renders are jobs
(202) polled at ``GET /api/jobs/{id}``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from fastapi import APIRouter
from fastapi.responses import FileResponse
from pydantic import Field

from app.errors import EditError, WorkbenchError
from app.fly_through import (
    RenderRequest,
    change_keyframes,
    is_render_name,
    list_renders,
    renders_folder,
    saved_path,
    start_render,
)
from app.routes.dependencies import REQUIRE_SESSION, Actor, ActorDep, SessionDep
from app.validation import MAX_INDEX, IndexPath, Point, Quaternion, RequestBody
from slam6d.camera_path import Keyframe
from slam6d.session import Session

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["fly-through"], dependencies=[REQUIRE_SESSION])


class KeyframeBody(RequestBody):
    position: Point
    orientation_wxyz: Quaternion | None = None
    look_at: Point | None = Field(None, description="instead of an orientation")
    fov_deg: float = Field(60.0, ge=1.0, lt=179.0)
    index: int | None = Field(None, ge=0, le=MAX_INDEX, description="insert before this keyframe (default: append)")

    def keyframe(self) -> Keyframe:
        if (self.orientation_wxyz is None) == (self.look_at is None):
            raise ValueError("give exactly one of orientation_wxyz and look_at")
        if self.look_at is not None:
            return Keyframe.looking_at(self.position, self.look_at, self.fov_deg)
        return Keyframe(np.asarray(self.position, float), np.asarray(self.orientation_wxyz, float), self.fov_deg)


class KeyframeList(RequestBody):
    keyframes: list[KeyframeBody] = Field(max_length=10_000)


class MoveBody(RequestBody):
    to: int = Field(ge=0, le=MAX_INDEX)


def _path_response(session: Session) -> dict[str, Any]:
    path = saved_path(session)
    keyframes = [] if path is None else path.to_dict()["keyframes"]
    return {
        "keyframes": keyframes,
        "duration": 0.0 if path is None else path.duration(),
        "default": path is None,  # renders follow the scan trajectory until keyframes are added
    }


def _edit(actor: Actor, change: Callable[[list[Keyframe]], object]) -> dict[str, Any]:
    """Apply ``change`` to the keyframes as stored when it is written (nobody else's edit is lost):
    404 for a keyframe index outside the path, 422 for a keyframe the camera path refuses."""
    session = actor.workbench.state(actor.session_id).session
    count = 0

    def checked(keyframes: list[Keyframe]) -> None:
        nonlocal count
        count = len(keyframes)
        change(keyframes)

    try:
        change_keyframes(actor.workbench, actor.session_id, checked, actor.author)
    except IndexError:
        raise EditError(f"no such keyframe; the path has {count}", 404) from None
    except ValueError as exc:
        raise WorkbenchError(str(exc)) from None
    return _path_response(session)


def _at(keyframes: list[Keyframe], index: int) -> int:
    if not 0 <= index < len(keyframes):
        raise IndexError(index)
    return index


@router.get("/camera-path")
def get_camera_path(state: SessionDep) -> dict[str, Any]:
    """The saved keyframes (position, orientation as w,x,y,z, vertical fov); empty: the default path."""
    return _path_response(state.session)


@router.put("/camera-path")
def put_camera_path(body: KeyframeList, actor: ActorDep) -> dict[str, Any]:
    """Replace all keyframes (an empty list goes back to the default path)."""

    def replace(keyframes: list[Keyframe]) -> None:
        keyframes[:] = [k.keyframe() for k in body.keyframes]

    return _edit(actor, replace)


@router.post("/camera-path/keyframes", status_code=201)
def add_keyframe(body: KeyframeBody, actor: ActorDep) -> dict[str, Any]:
    """Insert a keyframe (given by orientation or by a point to look at) before ``index``, or append it."""

    def add(keyframes: list[Keyframe]) -> None:
        index = len(keyframes) if body.index is None else body.index
        if not 0 <= index <= len(keyframes):
            raise IndexError(index)
        keyframes.insert(index, body.keyframe())

    return _edit(actor, add)


@router.post("/camera-path/keyframes/{index}/move")
def move_keyframe(index: IndexPath, body: MoveBody, actor: ActorDep) -> dict[str, Any]:
    """Move keyframe ``index`` to position ``to``."""

    def move(keyframes: list[Keyframe]) -> None:
        keyframes.insert(_at(keyframes, body.to), keyframes.pop(_at(keyframes, index)))

    return _edit(actor, move)


@router.delete("/camera-path/keyframes/{index}")
def delete_keyframe(index: IndexPath, actor: ActorDep) -> dict[str, Any]:
    return _edit(actor, lambda keyframes: keyframes.pop(_at(keyframes, index)))


@router.post("/render", status_code=202)
def post_render(body: RenderRequest, actor: ActorDep) -> dict[str, Any]:
    """Render a fly-through MP4 in the background; poll ``GET /api/jobs/{id}``, cancel with ``DELETE``."""
    return start_render(actor.workbench, actor.session_id, body, actor.author).as_dict()


@router.get("/renders")
def get_renders(session_id: str, state: SessionDep) -> list[dict[str, Any]]:
    """Finished renders, newest first, with their download URLs."""
    return list_renders(state.session, session_id)


@router.get("/renders/{name}")
def download_render(state: SessionDep, name: str) -> FileResponse:
    path = renders_folder(state.session) / name
    if not is_render_name(name) or not path.is_file():
        raise EditError(f"no render '{name}'", 404)
    return FileResponse(path, media_type="video/mp4", filename=name)
