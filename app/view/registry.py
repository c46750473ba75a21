"""Which sessions have a 3D view open: started when someone first opens a session, stopped when nobody looks.

A view is a viser server with its own port, threads and a copy of the scene: kept for every
session ever opened, a long-running server would hold them all. When its last browser leaves (or
no browser came at all), the view is stopped after ``grace_s`` seconds - long enough for a page
reload or a short network drop to find it still there; the next browser starts it again. A view
whose session has a job running or queued is kept (the job reports its progress there), and so is
one still reading its scans (the browser that asked for it is waiting). A session
with a view is in use: the memory budget does not release its scans.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from app.view.comment_labels import show_comments, show_when_ready
from app.view.presence import presence_of
from app.view.session_view import SessionViewer
from app.workbench import Workbench

log = logging.getLogger(__name__)


class ViewerRegistry:
    """Starts a session's viewer when someone first opens it; keeps it for everyone after."""

    def __init__(self, workbench: Workbench, grace_s: float | None = None) -> None:
        self.workbench = workbench
        self.grace_s = workbench.limits.viewer_grace_s if grace_s is None else grace_s
        self._viewers: dict[str, SessionViewer] = {}
        self._idle_since: dict[str, float] = {}  # session -> when its view last had no browser
        self._lock = threading.Lock()
        self.stopped_idle = 0  # views stopped for want of browsers (tests and logs)
        workbench.on_revision(self._on_revision)
        workbench.jobs.on_change(self._on_job)
        workbench.in_use_checks.append(lambda session_id: session_id in self._viewers)

    def get(self, session_id: str) -> SessionViewer:
        with self._lock:
            viewer = self._viewers.get(session_id)
            if viewer is None:
                viewer = self._viewers[session_id] = SessionViewer(self.workbench, session_id)
                presence_of(viewer)  # before any browser connects: who is who on it
                show_when_ready(viewer)  # its comments, once it has its scans
                viewer.server.on_client_connect(lambda _client: self._watched(session_id))
                viewer.server.on_client_disconnect(lambda _client: self._watch(session_id))
                self._watch_locked(session_id)  # a view nobody comes to is stopped too
            elif not viewer.server.get_clients():
                self._idle_since[session_id] = time.monotonic()  # asked for again: its grace starts anew
            return viewer

    def start(self, session_id: str) -> None:
        """Start the session's view in the background, for a page about to ask for it: the page is
        answered at once and its 3D client loads while the view starts (the view's websocket waits for
        it in :meth:`get`). Raises :class:`~app.errors.UnknownSessionError` for an unknown session."""
        self.workbench.state(session_id)
        if session_id in self._viewers:
            self.get(session_id)  # asked for again: its grace starts anew
            return
        threading.Thread(
            target=self._start_quietly, args=(session_id,), name=f"viewer-start-{session_id}", daemon=True
        ).start()

    def _start_quietly(self, session_id: str) -> None:
        try:
            self.get(session_id)
        except Exception:  # the page's websocket asks again and is answered the error
            log.exception("starting the 3D view of session %s failed", session_id)

    def _watched(self, session_id: str) -> None:
        """A browser is on the view: no grace period runs."""
        self._idle_since.pop(session_id, None)

    def _watch(self, session_id: str) -> None:
        with self._lock:
            self._watch_locked(session_id)

    def _watch_locked(self, session_id: str) -> None:
        self._idle_since[session_id] = time.monotonic()
        self._check_later(session_id, self.grace_s)

    def _check_later(self, session_id: str, delay: float) -> None:
        timer = threading.Timer(delay, self._stop_if_idle, args=(session_id,))
        timer.daemon = True
        timer.start()

    def _stop_if_idle(self, session_id: str) -> None:
        """Stop the view if no browser came back within the grace period (else look again later)."""
        with self._lock:
            viewer = self._viewers.get(session_id)
            since = self._idle_since.get(session_id)
            if viewer is None or since is None or viewer.server.get_clients():
                return
            left = since + self.grace_s - time.monotonic()
            if session_id in self.workbench.jobs.busy_sessions() or not viewer.ready.is_set():
                left = max(left, self.grace_s)  # a job's progress shows there; a loading view is awaited
            if left > 0:  # someone came and went meanwhile: their grace counts from then
                self._check_later(session_id, left)
                return
            del self._viewers[session_id]
            self._idle_since.pop(session_id, None)
            self.stopped_idle += 1
        viewer.stop()
        self.workbench.enforce_memory_budget()  # its session may now be released

    def existing(self, session_id: str) -> SessionViewer | None:
        return self._viewers.get(session_id)

    def _on_revision(self, session_id: str) -> None:
        viewer = self._viewers.get(session_id)
        if viewer is not None:
            viewer.on_revision()
            show_comments(viewer)  # notes on scans move with them; new ones appear

    def _on_job(self, job: Any) -> None:
        viewer = self._viewers.get(job.session_id)
        if viewer is not None:
            viewer.on_job(job)

    def stop_all(self) -> None:
        with self._lock:
            for viewer in self._viewers.values():
                viewer.stop()
            self._viewers.clear()
            self._idle_since.clear()
