"""What every part of a session's 3D view shares: the viser server, the session, the scans as shown, the lock.

The view is one object (:class:`app.view.session_view.SessionViewer`) assembled from parts that each
live in their own module - scene streaming, colouring, picking, playback, the graph overlay. Each
part sets up its own state; this base declares the state and the calls that cross from one part to
another, so each module reads (and type-checks) on its own.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import viser

from app.editing import Editor
from app.view.controls import ViewControls
from app.workbench import SessionState, Workbench
from slam6d.geometry import Matrix, rotation_to_quaternion

Colour = tuple[int, int, int]


class ViewCore:
    workbench: Workbench
    session_id: str
    state: SessionState
    editor: Editor
    server: viser.ViserServer
    controls: ViewControls
    lock: threading.RLock  # held while drawing, and by stop(): nothing is half-drawn when the server goes
    ready: threading.Event  # set once the first full pass of scans is sent (or loading failed)
    error: str | None
    stopped: bool
    local: list[np.ndarray]  # display points per scan, scanner frame, float32
    poses: list[Matrix]  # the poses the scans are shown at
    nodes: list[Any]  # the scans' point-cloud handles
    pose_version: int  # counts changes of the shown poses: what edge residuals were computed for
    light: dict[int, tuple[Any, np.ndarray]]  # playback: scan -> (light node, its point indices)
    focus: list[int] | None  # while stepping plays: the scans drawn in full
    residuals: list[np.ndarray] | None  # the colouring's per-point residuals, None once the poses change
    height_range: tuple[float, float]  # the height colouring's scale

    # calls between parts
    scan_colours: Callable[[int], np.ndarray | Colour]
    paint: Callable[[int], None]
    recolour: Callable[[], None]
    draw_graph: Callable[[], None]
    show_focus: Callable[[list[int]], None]
    add_cloud: Callable[..., Any]
    run_safely: Callable[[Callable[[], object]], None]
    warn: Callable[[str], None]
    update_status: Callable[[], None]


def place(node: Any, pose: Matrix) -> None:
    """Put a scene node at a pose (position and orientation; its points stay in the scan's frame)."""
    node.position = pose[:3, 3]
    node.wxyz = rotation_to_quaternion(pose[:3, :3])
