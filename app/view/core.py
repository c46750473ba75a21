"""What the parts of a session's 3D view share: the session and its viser server (:class:`ViewContext`)
and the scans as they are shown (:class:`ShownScans`).

The view is composed (:class:`app.view.session_view.SessionViewer` wires it): scene streaming,
colouring, playback, the graph overlay and picking are objects of their own, each given these two
and the other parts it calls, never the whole view. What one part changes that another must know
(the scans moved, were re-sent) goes through a method of that part, not through its attributes.
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from app.editing import Editor
from app.view.controls import ViewControls
from app.workbench import SessionState, Workbench
from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix, rotation_to_quaternion

Colour = tuple[int, int, int]

# what a button press may run into that the user can act on: shown as the message alone
USER_ERRORS = (Slam6dError, ValueError)


class ViewContext:
    """One session's view as every part sees it: the session, the viser server and its controls, the
    drawing lock, and whether the view is loaded, failed or stopped."""

    def __init__(self, workbench: Workbench, session_id: str, editor: Editor, server: viser.ViserServer) -> None:
        self.workbench = workbench
        self.session_id = session_id
        self.state: SessionState = workbench.state(session_id)
        self.editor = editor
        self.server = server
        self.controls = ViewControls(server.gui)
        # held while drawing, and by stop(): nothing is half-drawn when the server goes
        self.lock = threading.RLock()
        self.ready = threading.Event()  # set once the first full pass of scans is sent (or loading failed)
        self.error: str | None = None
        self.stopped = False

    def run_safely(self, action: Callable[[], object]) -> None:
        """GUI callbacks and the panels' background refreshes: an error the user can act on becomes a
        visible warning, not a dead button; anything else also leaves its traceback in the log. Once the
        view has stopped nothing runs: its server would drop the updates."""
        if self.stopped:
            return
        try:
            action()
        except USER_ERRORS as exc:
            self.warn(str(exc))
        except Exception as exc:
            traceback.print_exc()
            self.warn(f"{type(exc).__name__}: {exc}")

    def warn(self, message: str) -> None:
        self.controls.warnings.content = f"**⚠ {message}**" if message else ""


@dataclass
class ShownScans:
    """The scans as the browsers show them: display points in each scan's own frame, the poses they are
    drawn at, their scene nodes, and the light nodes playback shows in place of the full ones."""

    local: list[np.ndarray] = field(default_factory=list)  # display points per scan, scanner frame, float32
    poses: list[Matrix] = field(default_factory=list)
    nodes: list[Any] = field(default_factory=list)  # the scans' point-cloud handles
    light: dict[int, tuple[Any, np.ndarray]] = field(default_factory=dict)  # scan -> (light node, its indices)
    focus: list[int] | None = None  # while stepping plays: the scans drawn in full
    pose_version: int = 0  # counts changes of the shown poses: what edge residuals were computed for
    total_points: int = 0  # every scan's points at full resolution (from the level store: no scan read in full)

    def points_shown(self) -> int:
        return int(sum(len(p) for p in self.local))


def show_status(view: ViewContext, scans: ShownScans) -> None:
    """The status line (session, scans and points shown, revision) and the History folder's revision."""
    session = view.state.session
    total = scans.total_points
    view.controls.status.content = (
        f"**{session.name}** · {len(scans.local)} scans · {scans.points_shown():,} of {total:,} points shown · "
        f"revision {session.revision}"
    )
    view.controls.revision_text.content = (
        f"Revision {session.revision} (undo: {session.journal.can_undo()}, redo: {session.journal.can_redo()})"
    )


def send_cloud(
    view: ViewContext,
    name: str,
    points: np.ndarray,
    colours: np.ndarray | tuple[int, int, int],
    pose: Matrix,
    precision: str,
    visible: bool = True,
) -> Any:
    """A scan's points in its own frame, placed by its pose on the node (never world coordinates)."""
    return view.server.scene.add_point_cloud(
        name,
        points=points,
        colors=colours,
        point_size=float(view.controls.point_size.value),
        point_shading="flat",  # no per-pixel sphere shading: ~15 % faster frames without a GPU
        precision=precision,  # type: ignore[arg-type]
        position=pose[:3, 3],
        wxyz=rotation_to_quaternion(pose[:3, :3]),
        visible=visible,
    )


def place(node: Any, pose: Matrix) -> None:
    """Put a scene node at a pose (position and orientation; its points stay in the scan's frame)."""
    node.position = pose[:3, 3]
    node.wxyz = rotation_to_quaternion(pose[:3, :3])
