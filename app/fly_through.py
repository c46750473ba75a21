"""Fly-through renders in the workbench: a camera path built from views in the browser, rendered on the server.

The path lives in the session (``Session.set_camera_path``): every edit - a keyframe added from a
browser's current view, moved or deleted, from the 3D view's "Fly-through" panel or from REST - is
saved at once, so every browser and ``slam6d render SESSION`` see the same path, and the journal
records who changed it. With no keyframes the default path (following the scan trajectory) is used.

Renders run as background jobs (progress, cancel) and land in ``SESSION/renders/`` as MP4 files,
served for download by ``GET /api/sessions/{id}/renders/{name}``. This module holds the path and the
render jobs; the REST routes are :mod:`app.routes.camera_path`, the panel
:mod:`app.view.panels.fly_through`. The renderer writes to a hidden
temporary name and moves it into place at the end, so a cancelled render leaves no file behind.
"""

from __future__ import annotations

import itertools
import math
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, Field

from app.errors import WorkbenchError
from app.jobs import Cancel, Job, Progress, Work
from app.workbench import Workbench
from slam6d.camera_path import CameraPath, Keyframe, camera_path_from_dict, trajectory_path
from slam6d.geometry import Matrix
from slam6d.point_scene import COLOR_MODES, scene_from_sequence
from slam6d.render import SHADINGS, RenderOptions, render_fly_through
from slam6d.session import Session

RENDERS_DIR = "renders"
RENDER_KIND = "render"
SIZES = ("320x240", "640x480", "1280x720", "1920x1080")
_RENDER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}\.mp4$")
_names = itertools.count(1)


# ------------------------------------------------------------------ the path saved in a session


def saved_path(session: Session) -> CameraPath | None:
    """The session's keyframes as a path, or None while the user has not added any."""
    keyframes = session.camera_path()
    return camera_path_from_dict({"keyframes": keyframes}, source=session.folder) if keyframes else None


def keyframes_of(session: Session) -> list[Keyframe]:
    path = saved_path(session)
    return [] if path is None else list(path.keyframes)


def save_keyframes(workbench: Workbench, session_id: str, keyframes: list[Keyframe], author: str) -> None:
    """Store the keyframes in the session and tell the 3D views of that session to redraw them."""
    session = workbench.state(session_id).session
    session.set_camera_path(CameraPath(list(keyframes)).to_dict()["keyframes"], author)
    workbench.camera_path_changed(session_id)


def path_for_render(session: Session, scan_poses: list[Matrix]) -> CameraPath:
    """What a render follows: the user's keyframes, else the default path along the scans."""
    return saved_path(session) or trajectory_path(scan_poses)


def keyframe_from_view(position: Any, wxyz: Any, fov_rad: float) -> Keyframe:
    """A browser camera (viser: world_from_camera, OpenCV axes, like the renderer) as a keyframe."""
    return Keyframe(np.asarray(position, dtype=np.float64), np.asarray(wxyz, dtype=np.float64), math.degrees(fov_rad))


# ------------------------------------------------------------------ render jobs


class RenderRequest(BaseModel):
    width: int = Field(640, ge=16, le=3840, description="pixels; even (H.264)")
    height: int = Field(480, ge=16, le=2160, description="pixels; even (H.264)")
    fps: float = Field(30.0, gt=0.0, le=120.0)
    frames: int | None = Field(None, ge=1, le=100_000, description="default: from the path's length and pace")
    name: str | None = Field(None, description="file name in the session's renders/ folder (…mp4)")
    color: str = "height"
    shading: str = "edl+depth"
    point_size: float = Field(0.03, ge=0.0, le=1.0, description="splat size in metres")
    max_points: int = Field(2_000_000, ge=1_000, le=50_000_000)


def is_render_name(name: str) -> bool:
    """A name a render may have: no folders, no hidden files, ending in .mp4 (what downloads accept)."""
    return bool(_RENDER_NAME.match(name))


def renders_folder(session: Session) -> Path:
    return session.folder / RENDERS_DIR


def download_url(session_id: str, name: str) -> str:
    return f"/api/sessions/{session_id}/renders/{name}"


def list_renders(session: Session, session_id: str) -> list[dict[str, Any]]:
    """Finished renders, newest first (the renderer's hidden partial files are not listed)."""
    folder = renders_folder(session)
    files = [p for p in folder.glob("*.mp4") if _RENDER_NAME.match(p.name)] if folder.is_dir() else []
    files.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    return [
        {
            "name": p.name,
            "bytes": p.stat().st_size,
            "modified": p.stat().st_mtime,
            "url": download_url(session_id, p.name),
        }
        for p in files
    ]


def render_job(workbench: Workbench, session_id: str, request: RenderRequest) -> tuple[Work, dict[str, Any]]:
    """Validate a render request now (so a bad one is refused before any work) and return the job's work.

    The path is fixed when the job starts: edits made while it renders apply to the next render.
    """
    state = workbench.state(session_id)
    session = state.session
    if request.width % 2 or request.height % 2:
        raise WorkbenchError(f"H.264 needs an even width and height, got {request.width}x{request.height}")
    if request.color not in COLOR_MODES or request.shading not in SHADINGS:
        raise WorkbenchError(
            f"colour must be one of {', '.join(COLOR_MODES)} and shading one of {', '.join(SHADINGS)}, "
            f"got {request.color!r} and {request.shading!r}"
        )
    options = RenderOptions(color_mode=request.color, shading=request.shading, point_size=request.point_size)
    name = request.name or f"flythrough-{time.strftime('%Y%m%d-%H%M%S')}-{next(_names)}.mp4"
    if not _RENDER_NAME.match(name):
        raise WorkbenchError(f"render name '{name}' is not allowed (letters, digits, '.', '_', '-', ending in .mp4)")
    out = renders_folder(session) / name
    if out.exists():
        raise WorkbenchError(f"a render named '{name}' already exists", 409)
    user_path = saved_path(session)

    def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
        sequence = state.sequence(lambda d, t: progress("reading scans", d, t))
        with state.lock:  # poses may change under an edit; take one consistent snapshot
            scene = scene_from_sequence(sequence, request.max_points)
        path = user_path or trajectory_path(scene.scan_poses)
        out.parent.mkdir(exist_ok=True)
        result = render_fly_through(
            scene,
            out,
            request.width,
            request.height,
            request.fps,
            request.frames,
            path,
            options,
            progress=lambda d, t: progress("rendering", d, t),
            cancel=cancel,
        )
        return {
            "name": name,
            "url": download_url(session_id, name),
            "frames": result.frames,
            "width": result.width,
            "height": result.height,
            "fps": result.fps,
            "seconds": round(result.seconds, 3),
            "points": result.points,
            "path": "keyframes" if user_path is not None else "trajectory",
        }

    return work, {**request.model_dump(), "name": name}


def start_render(workbench: Workbench, session_id: str, request: RenderRequest, author: str) -> Job:
    work, parameters = render_job(workbench, session_id, request)
    return workbench.jobs.submit(session_id, RENDER_KIND, work, author, parameters)
