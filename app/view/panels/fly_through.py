"""The "Fly-through" folder of a session's 3D view: keyframes from the browser's camera, a preview flight, renders.

The path and the render jobs are :mod:`app.fly_through`'s, so this panel and the REST routes edit
the same saved path; every 3D view of the session redraws it when it changes.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

from app.fly_through import (
    RENDER_KIND,
    SIZES,
    RenderRequest,
    change_keyframes,
    keyframe_from_view,
    keyframes_of,
    list_renders,
    start_render,
)
from app.view.panels.host import ViewerHost
from app.view.panels.progress import show_job_progress
from slam6d.camera_path import CameraPath, Keyframe, trajectory_path
from slam6d.geometry import Matrix, rotation_to_quaternion

_FLY_RATE = 30.0  # camera updates per second of the in-browser preview flight
_MAX_FLY_FRAMES = 1800


class FlyThroughPanel:
    """The "Fly-through" folder of a session's 3D view, shared (like everything there) by all its browsers."""

    def __init__(self, viewer: ViewerHost) -> None:
        self.viewer = viewer
        self.workbench = viewer.workbench
        self.session_id = viewer.session_id
        self.session = viewer.state.session
        self.job_id: str | None = None
        self._frustums: list[Any] = []
        self._flying = threading.Event()
        self._draw_lock = threading.Lock()  # edits arrive from REST threads, GUI callbacks and jobs at once
        self._build_gui()
        self.workbench.on_camera_path(self._on_path)
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
        added = keyframe_from_view(camera.position, camera.wxyz, camera.fov)
        change_keyframes(
            self.workbench, self.session_id, lambda keyframes: keyframes.append(added), self.viewer.author(event)
        )

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
        shown = keyframes[index]
        target = -1

        def edit(stored: list[Keyframe]) -> None:  # on the keyframes as stored now: the one shown, if still there
            nonlocal target
            at = next((n for n, k in enumerate(stored) if _same_view(k, shown)), None)
            if at is None:
                raise ValueError("that keyframe was changed by someone else meanwhile; pick it again")
            if action == "Delete":
                stored.pop(at)
                target = min(at, len(stored) - 1)
            else:
                target = max(0, at - 1) if action == "Up" else min(len(stored) - 1, at + 1)
                stored.insert(target, stored.pop(at))

        change_keyframes(self.workbench, self.session_id, edit, self.viewer.author(event))
        if target >= 0:
            self.selected.value = str(target + 1)  # type: ignore[misc]  # the moved keyframe stays selected

    @staticmethod
    def _labels(count: int) -> tuple[str, ...]:
        return tuple(str(i + 1) for i in range(count))

    def path_changed(self) -> None:
        """The saved path changed (from this panel, another browser or REST): redraw list and preview."""
        self.viewer.run_safely(self.draw)

    def _on_path(self, session_id: str) -> None:
        if session_id == self.session_id:
            self.path_changed()

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
        poses = list(self.viewer.scans.poses)
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


def _same_view(a: Keyframe, b: Keyframe) -> bool:
    """Whether two keyframes are the same view (as stored: JSON round trips keep floats exactly)."""
    return bool(
        np.allclose(a.position, b.position, atol=1e-9)
        and np.allclose(a.orientation, b.orientation, atol=1e-9)
        and abs(a.fov_deg - b.fov_deg) < 1e-9
    )
