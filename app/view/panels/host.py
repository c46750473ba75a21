"""The part of the session's 3D view that its panels use."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

import viser

from app.view.colouring import Colouring
from app.view.controls import ViewControls
from app.view.core import ShownScans
from app.view.graph_overlay import GraphOverlay
from app.view.picking import Picking
from app.workbench import SessionState, Workbench
from slam6d.geometry import Matrix


class ViewerHost(Protocol):
    """What a panel may use of the session's 3D view (:class:`app.view.session_view.SessionViewer`).

    Written out so that panels depend on this narrow surface, not on the viewer module, which
    builds them: the view and its panels then import in one direction only.
    """

    workbench: Workbench
    session_id: str
    state: SessionState
    server: viser.ViserServer
    ready: threading.Event
    lock: threading.RLock  # held while drawing, and by stop(): nothing is half-drawn when the server goes
    stopped: bool
    error: str | None
    scans: ShownScans  # the scans as shown: display points, poses, nodes
    colouring: Colouring  # highlight, selection, component colours
    graph: GraphOverlay
    picking: Picking
    controls: ViewControls  # the view's own folders: the ICP plot, play/pause, the stepping status

    def author(self, event: Any) -> str: ...
    def warn(self, message: str) -> None: ...
    def run_safely(self, action: Callable[[], object]) -> None: ...
    def set_poses(self, poses: list[Matrix], indices: list[int] | None = None) -> None: ...
    def on_revision(self) -> None: ...
    def begin_playback(self, focus: list[int]) -> None: ...
    def end_playback(self) -> None: ...
