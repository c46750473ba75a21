"""Fly-through renders in the workbench: a camera path built from views in the browser, rendered on the server.

The path lives in the session (``Session.set_camera_path``): every edit - a keyframe added from a
browser's current view, moved or deleted, from the 3D view's "Fly-through" panel or from REST - is
saved at once, so every browser and ``slam6d render SESSION`` see the same path, and the journal
records who changed it. With no keyframes the default path (following the scan trajectory) is used.

Renders run as background jobs (progress, cancel) and land in ``SESSION/renders/`` as MP4 files,
served for download by ``GET /api/sessions/{id}/renders/{name}``. The renderer writes to a hidden
temporary name and moves it into place at the end, so a cancelled render leaves no file behind.
"""

from __future__ import annotations

import itertools
import math
import re
import threading
import time
import weakref
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Header, HTTPException
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from app.jobs import JobConflictError, Work
from app.panels.host import ViewerHost
from app.panels.progress import show_job_progress
from app.workbench import UnknownSessionError, Workbench
from slam6d.camera_path import CameraPath, Keyframe, camera_path_from_dict, trajectory_path
from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix, rotation_to_quaternion
from slam6d.point_scene import COLOR_MODES, scene_from_sequence
from slam6d.render import SHADINGS, RenderOptions, render_fly_through
from slam6d.session import Session

RENDERS_DIR = "renders"
RENDER_KIND = "render"
SIZES = ("320x240", "640x480", "1280x720", "1920x1080")
_RENDER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}\.mp4$")
_FLY_RATE = 30.0  # camera updates per second of the in-browser preview flight
_MAX_FLY_FRAMES = 1800
_names = itertools.count(1)

Author = Annotated[str, Header(alias="X-Author", max_length=100)]
_panels: weakref.WeakSet[RenderPanel] = weakref.WeakSet()  # open 3D views, told when a saved path changes


# ------------------------------------------------------------------ the path saved in a session


def saved_path(session: Session) -> CameraPath | None:
    """The session's keyframes as a path, or None while the user has not added any."""
    keyframes = session.camera_path()
    return camera_path_from_dict({"keyframes": keyframes}, source=session.folder) if keyframes else None


def keyframes_of(session: Session) -> list[Keyframe]:
    path = saved_path(session)
    return [] if path is None else list(path.keyframes)


def save_keyframes(session: Session, keyframes: list[Keyframe], author: str) -> None:
    """Store the keyframes in the session and tell the 3D views of that session to redraw them."""
    session.set_camera_path(CameraPath(list(keyframes)).to_dict()["keyframes"], author)
    for panel in list(_panels):
        if panel.folder == session.folder:
            panel.path_changed()


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
        raise ValueError(f"H.264 needs an even width and height, got {request.width}x{request.height}")
    if request.color not in COLOR_MODES or request.shading not in SHADINGS:
        raise ValueError(
            f"colour must be one of {', '.join(COLOR_MODES)} and shading one of {', '.join(SHADINGS)}, "
            f"got {request.color!r} and {request.shading!r}"
        )
    options = RenderOptions(color_mode=request.color, shading=request.shading, point_size=request.point_size)
    name = request.name or f"flythrough-{time.strftime('%Y%m%d-%H%M%S')}-{next(_names)}.mp4"
    if not _RENDER_NAME.match(name):
        raise ValueError(f"render name '{name}' is not allowed (letters, digits, '.', '_', '-', ending in .mp4)")
    out = renders_folder(session) / name
    if out.exists():
        raise FileExistsError(f"a render named '{name}' already exists")
    user_path = saved_path(session)

    def work(progress, cancel):  # type: ignore[no-untyped-def]
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


def start_render(workbench: Workbench, session_id: str, request: RenderRequest, author: str):  # type: ignore[no-untyped-def]
    work, parameters = render_job(workbench, session_id, request)
    return workbench.jobs.submit(session_id, RENDER_KIND, work, author, parameters)


# ------------------------------------------------------------------ REST


class KeyframeBody(BaseModel):
    position: list[float] = Field(min_length=3, max_length=3)
    orientation_wxyz: list[float] | None = Field(None, min_length=4, max_length=4)
    look_at: list[float] | None = Field(None, min_length=3, max_length=3, description="instead of an orientation")
    fov_deg: float = 60.0
    index: int | None = Field(None, description="insert before this keyframe (default: append)")

    def keyframe(self) -> Keyframe:
        if (self.orientation_wxyz is None) == (self.look_at is None):
            raise ValueError("give exactly one of orientation_wxyz and look_at")
        if self.look_at is not None:
            return Keyframe.looking_at(self.position, self.look_at, self.fov_deg)
        return Keyframe(np.asarray(self.position, float), np.asarray(self.orientation_wxyz, float), self.fov_deg)


class KeyframeList(BaseModel):
    keyframes: list[KeyframeBody]


class MoveBody(BaseModel):
    to: int = Field(ge=0)


def _path_response(session: Session) -> dict[str, Any]:
    path = saved_path(session)
    keyframes = [] if path is None else path.to_dict()["keyframes"]
    return {
        "keyframes": keyframes,
        "duration": 0.0 if path is None else path.duration(),
        "default": path is None,  # renders follow the scan trajectory until keyframes are added
    }


def build_render_router(workbench: Workbench) -> APIRouter:
    router = APIRouter(prefix="/api/sessions/{session_id}")

    def session_of(session_id: str) -> Session:
        try:
            return workbench.state(session_id).session
        except UnknownSessionError:
            raise HTTPException(404, f"no session '{session_id}'") from None
        except Slam6dError as exc:
            raise HTTPException(422, str(exc)) from None

    def edit(session: Session, change, author: str) -> dict[str, Any]:  # type: ignore[no-untyped-def]
        keyframes = keyframes_of(session)
        try:
            change(keyframes)
        except IndexError:
            raise HTTPException(404, f"no such keyframe; the path has {len(keyframes)}") from None
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        save_keyframes(session, keyframes, author)
        return _path_response(session)

    def at(keyframes: list[Keyframe], index: int) -> int:
        if not 0 <= index < len(keyframes):
            raise IndexError(index)
        return index

    @router.get("/camera-path")
    def get_camera_path(session_id: str) -> dict[str, Any]:
        """The saved keyframes (position, orientation as w,x,y,z, vertical fov); empty: the default path."""
        return _path_response(session_of(session_id))

    @router.put("/camera-path")
    def put_camera_path(session_id: str, body: KeyframeList, author: Author = "anonymous") -> dict[str, Any]:
        """Replace all keyframes (an empty list goes back to the default path)."""
        session = session_of(session_id)

        def replace(keyframes: list[Keyframe]) -> None:
            keyframes[:] = [k.keyframe() for k in body.keyframes]

        return edit(session, replace, author)

    @router.post("/camera-path/keyframes", status_code=201)
    def add_keyframe(session_id: str, body: KeyframeBody, author: Author = "anonymous") -> dict[str, Any]:
        session = session_of(session_id)

        def add(keyframes: list[Keyframe]) -> None:
            index = len(keyframes) if body.index is None else body.index
            if not 0 <= index <= len(keyframes):
                raise IndexError(index)
            keyframes.insert(index, body.keyframe())

        return edit(session, add, author)

    @router.post("/camera-path/keyframes/{index}/move")
    def move_keyframe(session_id: str, index: int, body: MoveBody, author: Author = "anonymous") -> dict[str, Any]:
        session = session_of(session_id)

        def move(keyframes: list[Keyframe]) -> None:
            keyframes.insert(at(keyframes, body.to), keyframes.pop(at(keyframes, index)))

        return edit(session, move, author)

    @router.delete("/camera-path/keyframes/{index}")
    def delete_keyframe(session_id: str, index: int, author: Author = "anonymous") -> dict[str, Any]:
        session = session_of(session_id)
        return edit(session, lambda keyframes: keyframes.pop(at(keyframes, index)), author)

    @router.post("/render", status_code=202)
    def post_render(session_id: str, body: RenderRequest, author: Author = "anonymous") -> dict[str, Any]:
        """Render a fly-through MP4 in the background; poll ``GET /api/jobs/{id}``, cancel with ``DELETE``."""
        session_of(session_id)
        try:
            job = start_render(workbench, session_id, body, author)
        except (FileExistsError, JobConflictError) as exc:
            raise HTTPException(409, str(exc)) from None
        except (Slam6dError, ValueError) as exc:
            raise HTTPException(422, str(exc)) from None
        return job.as_dict()

    @router.get("/renders")
    def get_renders(session_id: str) -> list[dict[str, Any]]:
        return list_renders(session_of(session_id), session_id)

    @router.get("/renders/{name}")
    def download_render(session_id: str, name: str) -> FileResponse:
        session = session_of(session_id)
        if not _RENDER_NAME.match(name):
            raise HTTPException(404, f"no render '{name}'")
        path = renders_folder(session) / name
        if not path.is_file():
            raise HTTPException(404, f"no render '{name}'")
        return FileResponse(path, media_type="video/mp4", filename=name)

    return router


# ------------------------------------------------------------------ the panel in the 3D view


class RenderPanel:
    """The "Fly-through" folder of a session's 3D view, shared (like everything there) by all its browsers."""

    def __init__(self, viewer: ViewerHost) -> None:
        self.viewer = viewer
        self.workbench = viewer.workbench
        self.session_id = viewer.session_id
        self.session = viewer.state.session
        self.folder = self.session.folder
        self.job_id: str | None = None
        self._frustums: list[Any] = []
        self._flying = threading.Event()
        self._draw_lock = threading.Lock()  # edits arrive from REST threads, GUI callbacks and jobs at once
        self._build_gui()
        _panels.add(self)
        self.workbench.jobs.on_change(self._on_job)
        self.workbench.on_revision(self._on_revision)
        threading.Thread(target=self._draw_when_loaded, name=f"render-panel-{self.session_id}", daemon=True).start()

    # -------------------------------------------------------------- GUI

    def _build_gui(self) -> None:
        gui = self.viewer.server.gui
        with gui.add_folder("Fly-through", expand_by_default=False):
            self.add_button = gui.add_button("Add keyframe from view", hint="the current camera of your browser")
            self.keyframe_table = gui.add_markdown("")
            self.selected = gui.add_dropdown("Keyframe", ("–",), disabled=True)
            self.edit_buttons = gui.add_button_group("Edit", ("Up", "Down", "Delete", "Go to"))
            self.show_path = gui.add_checkbox("Show path", True)
            self.fly_button = gui.add_button("Fly along path", hint="preview: moves your camera along the path")
            self.size = gui.add_dropdown("Size", SIZES, initial_value="640x480")
            self.fps = gui.add_number("Video fps", 30, min=1, max=120, step=1)
            self.frames = gui.add_number("Frames (0: from path)", 0, min=0, max=100_000, step=1)
            self.render_button = gui.add_button("Render video")
            self.cancel_button = gui.add_button("Cancel render", disabled=True)
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.render_status = gui.add_markdown("")
            self.downloads = gui.add_html("")
        self.add_button.on_click(lambda e: self.viewer.run_safely(lambda: self._add_from_view(e)))
        self.edit_buttons.on_click(lambda e: self.viewer.run_safely(lambda: self._edit(e)))
        self.show_path.on_update(lambda _: self.viewer.run_safely(self.draw))
        self.fly_button.on_click(lambda e: self.viewer.run_safely(lambda: self._fly(e)))
        self.render_button.on_click(lambda e: self.viewer.run_safely(lambda: self._render(e)))
        self.cancel_button.on_click(lambda _: self._cancel())

    def _cancel(self) -> None:
        if self.job_id:
            self.workbench.jobs.cancel(self.job_id)

    def _add_from_view(self, event: Any) -> None:
        client = event.client
        if client is None:
            raise ValueError("no browser camera to take the view from")
        camera = client.camera
        keyframes = keyframes_of(self.session)
        keyframes.append(keyframe_from_view(camera.position, camera.wxyz, camera.fov))
        save_keyframes(self.session, keyframes, self.viewer.author(event))

    def _edit(self, event: Any) -> None:
        keyframes = keyframes_of(self.session)
        if self.selected.value not in self._labels(len(keyframes)):
            return
        index = int(self.selected.value) - 1
        action = self.edit_buttons.value
        if action == "Go to":
            if event.client is not None:
                self._move_camera(event.client, keyframes[index].pose(), keyframes[index].fov_deg)
            return
        if action == "Delete":
            keyframes.pop(index)
            target = min(index, len(keyframes) - 1)
        else:
            target = max(0, index - 1) if action == "Up" else min(len(keyframes) - 1, index + 1)
            keyframes.insert(target, keyframes.pop(index))
        save_keyframes(self.session, keyframes, self.viewer.author(event))
        if target >= 0:
            self.selected.value = str(target + 1)  # type: ignore[misc]  # the moved keyframe stays selected

    @staticmethod
    def _labels(count: int) -> tuple[str, ...]:
        return tuple(str(i + 1) for i in range(count))

    def path_changed(self) -> None:
        """The saved path changed (from this panel, another browser or REST): redraw list and preview."""
        self.viewer.run_safely(self.draw)

    def _on_revision(self, session_id: str) -> None:
        if session_id == self.session_id and self.viewer.ready.is_set() and not keyframes_of(self.session):
            self.path_changed()  # the default path follows the scans, which just moved

    def draw(self) -> None:
        # the view's lock first (a revision redraws while holding it), and nothing once it has stopped
        with self.viewer.lock, self._draw_lock:
            if not self.viewer.stopped:
                self._draw()

    def _draw(self) -> None:
        keyframes = keyframes_of(self.session)
        labels = self._labels(len(keyframes))
        previous = self.selected.value
        self.selected.options = labels or ("–",)
        self.selected.value = previous if previous in labels else (labels[-1] if labels else "–")  # type: ignore[misc]
        self.selected.disabled = not labels
        rows = [
            f"| {i + 1} | {k.position[0]:.1f}, {k.position[1]:.1f}, {k.position[2]:.1f} | {k.fov_deg:.0f}° |"
            for i, k in enumerate(keyframes)
        ]
        path = self._preview_path(keyframes)
        if keyframes:
            duration = path.duration() if path is not None else 0.0
            header = [f"{len(keyframes)} keyframe(s), {duration:.1f} s of video", "", "| # | position (m) | fov |"]
            self.keyframe_table.content = "\n".join([*header, "|---|---|---|", *rows])
        else:
            self.keyframe_table.content = "No keyframes: renders follow the scan trajectory (dashed preview)."
        self._draw_preview(keyframes, path)
        self._show_downloads()

    def _preview_path(self, keyframes: list[Keyframe]) -> CameraPath | None:
        if keyframes:
            return CameraPath(keyframes)
        poses = list(self.viewer.poses)
        return trajectory_path(poses) if poses else None

    def _draw_preview(self, keyframes: list[Keyframe], path: CameraPath | None) -> None:
        scene = self.viewer.server.scene
        for handle in self._frustums:
            handle.remove()
        self._frustums = []
        visible = bool(self.show_path.value)
        if path is None or len(path.keyframes) < 2:
            scene.add_line_segments(
                "/flythrough/path", np.zeros((1, 2, 3), np.float32), colors=(0, 0, 0), visible=False
            )
        else:
            points = path.preview(300)
            origin = points[0].copy()
            segments = np.stack([points[:-1], points[1:]], axis=1) - origin
            if not keyframes:  # the default path: every other segment, so it reads as dashed
                segments = segments[::2]
            scene.add_line_segments(
                "/flythrough/path",
                segments.astype(np.float32),
                colors=(80, 220, 255),
                thickness=3.0,
                thickness_units="screen",
                position=origin,
                visible=visible,
            )
        for i, k in enumerate(keyframes):
            self._frustums.append(
                scene.add_camera_frustum(
                    f"/flythrough/keyframes/{i + 1}",
                    fov=math.radians(k.fov_deg),
                    aspect=self._aspect(),
                    scale=0.4,
                    thickness=2.0,
                    thickness_units="screen",
                    color=(80, 220, 255),
                    wxyz=k.orientation,
                    position=k.position,
                    visible=visible,
                )
            )

    def _aspect(self) -> float:
        width, height = (int(v) for v in str(self.size.value).split("x"))
        return width / height

    def _draw_when_loaded(self) -> None:
        self.viewer.ready.wait()
        if not self.viewer.error:
            self.path_changed()

    # -------------------------------------------------------------- fly preview

    def _fly(self, event: Any) -> None:
        client = event.client
        path = self._preview_path(keyframes_of(self.session))
        if client is None or path is None:
            raise ValueError("nothing to fly along yet: add keyframes or load scans")
        if self._flying.is_set():
            self._flying.clear()  # a second click stops the flight
            return
        count = min(path.frame_count(_FLY_RATE), _MAX_FLY_FRAMES)
        samples = path.sample(frames=max(count, 2))
        self._flying.set()

        def fly() -> None:
            try:
                for pose, fov in samples:
                    if not self._flying.is_set():
                        break
                    start = time.monotonic()
                    self._move_camera(client, pose, fov)
                    time.sleep(max(0.0, 1.0 / _FLY_RATE - (time.monotonic() - start)))
            except Exception as exc:  # the browser may have gone away mid-flight
                self.viewer.warn(f"preview stopped: {exc}")
            finally:
                self._flying.clear()

        threading.Thread(target=fly, name="fly-preview", daemon=True).start()

    @staticmethod
    def _move_camera(client: Any, pose: Matrix, fov_deg: float) -> None:
        with client.atomic():
            client.camera.position = pose[:3, 3]
            client.camera.wxyz = rotation_to_quaternion(pose[:3, :3])
            client.camera.fov = math.radians(fov_deg)

    # -------------------------------------------------------------- rendering

    def _render(self, event: Any) -> None:
        width, height = (int(v) for v in str(self.size.value).split("x"))
        frames = int(self.frames.value)
        request = RenderRequest(width=width, height=height, fps=float(self.fps.value), frames=frames or None)
        job = start_render(self.workbench, self.session_id, request, self.viewer.author(event))
        self.job_id = job.id

    def _on_job(self, job: Any) -> None:
        if job.session_id != self.session_id or job.kind != RENDER_KIND:
            return
        self.job_id = job.id
        show_job_progress(job, self.render_button, self.cancel_button, self.progress, self.render_status, "Rendering")
        if job.active:
            return
        if job.status == "done":
            result = job.result
            self.render_status.content = (
                f"Rendered {result['frames']} frames {result['width']}x{result['height']} in {result['seconds']:.1f} s"
            )
            self._show_downloads()
        else:
            self.render_status.content = f"Render {job.status}" + (f": {job.message}" if job.status == "failed" else "")

    def _show_downloads(self) -> None:
        renders = list_renders(self.session, self.session_id)[:5]
        links = [
            f'<li><a class="render-download" href="{r["url"]}" download="{r["name"]}">{r["name"]}</a> '
            f"({r['bytes'] / 1e6:.1f} MB)</li>"
            for r in renders
        ]
        self.downloads.content = f"<p>Download:</p><ul>{''.join(links)}</ul>" if links else ""
