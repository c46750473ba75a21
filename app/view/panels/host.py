"""The part of the session's 3D view that its panels use."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import viser

from app.view.controls import ViewControls
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
    poses: list[Matrix]
    local: list[np.ndarray]  # display points per scan, scanner frame
    nodes: list[Any]  # the scans' point-cloud handles
    highlight: dict[int, tuple[int, int, int]]
    component_of: dict[int, int]  # scan -> its connected component, for the "component" colouring
    controls: ViewControls  # the view's own folders: the ICP plot, play/pause, the stepping status

    def author(self, event: Any) -> str: ...
    def warn(self, message: str) -> None: ...
    def run_safely(self, action: Callable[[], object]) -> None: ...
    def set_poses(self, poses: list[Matrix], indices: list[int] | None = None) -> None: ...
    def select(self, selected: dict[int, tuple[int, int, int]]) -> None: ...
    def pick(self, ray_origin: Any, ray_direction: Any) -> int | None: ...
    def scan_colours(self, k: int) -> np.ndarray | tuple[int, int, int]: ...
    def recolour(self) -> None: ...
    def draw_graph(self) -> None: ...
    def on_revision(self) -> None: ...
    def paint(self, k: int) -> None: ...
    def begin_playback(self, focus: list[int]) -> None: ...
    def end_playback(self) -> None: ...
