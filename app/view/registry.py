"""Which sessions have a 3D view open: started when someone first opens a session, kept for everyone after."""

from __future__ import annotations

import threading
from typing import Any

from app.view.session_view import SessionViewer
from app.workbench import Workbench


class ViewerRegistry:
    """Starts a session's viewer when someone first opens it; keeps it for everyone after."""

    def __init__(self, workbench: Workbench) -> None:
        self.workbench = workbench
        self._viewers: dict[str, SessionViewer] = {}
        self._lock = threading.Lock()
        workbench.on_revision(self._on_revision)
        workbench.jobs.on_change(self._on_job)

    def get(self, session_id: str) -> SessionViewer:
        with self._lock:
            viewer = self._viewers.get(session_id)
            if viewer is None:
                viewer = self._viewers[session_id] = SessionViewer(self.workbench, session_id)
            return viewer

    def existing(self, session_id: str) -> SessionViewer | None:
        return self._viewers.get(session_id)

    def _on_revision(self, session_id: str) -> None:
        viewer = self._viewers.get(session_id)
        if viewer is not None:
            viewer.on_revision()

    def _on_job(self, job: Any) -> None:
        viewer = self._viewers.get(job.session_id)
        if viewer is not None:
            viewer.on_job(job)

    def stop_all(self) -> None:
        with self._lock:
            for viewer in self._viewers.values():
                viewer.stop()
            self._viewers.clear()
