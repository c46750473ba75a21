"""Scene streaming: the session's scans sent to the browsers as levels of detail within a point budget, coarse first, then moved by pose.

Scans are sent (at levels of detail read from the session's cache, :mod:`app.view.detail_stream`) in their own frame, so the points go over the
wire once and moving a scan only changes its scene node's pose. This is the only place point data
is sent; everything else (colours, playback, the graph) changes nodes that are already there.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np

from app.view import display
from app.view.colouring import Colouring
from app.view.core import ShownScans, ViewContext, place, send_cloud, show_status
from app.view.detail_stream import DetailStream
from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix
from slam6d.scan_levels import session_levels

_CLIENT_WAIT = 5.0  # s: how long the full pass waits for the browser that opened the session to connect
_COARSE_SETTLE = 0.5  # s: time for a browser to take in the coarse pass before the full one follows


class SceneStream:
    def __init__(
        self,
        view: ViewContext,
        scans: ShownScans,
        colouring: Colouring,
        show_focus: Callable[[list[int]], None],
        draw_graph: Callable[[], None],
        before_full_pass: Callable[[], None] = lambda: None,
    ) -> None:
        self.view = view
        self.scans = scans
        self.colouring = colouring
        self.show_focus = show_focus  # playback's: a re-sent map keeps showing the current pair in full
        self.draw_graph = draw_graph  # the graph overlay follows the scans
        self.before_full_pass = before_full_pass  # once, after the first look went out: the view's secondary panels
        self.shown_revision = -1  # the journal revision whose poses are shown
        self.coarse_points = 0  # points of the coarse first pass (0: the budget was sent in one pass)
        self.pose_updates = 0
        self.client_seen = threading.Event()  # a browser has connected to this view
        self.detail: DetailStream | None = None  # the scans' levels of detail, once loaded
        self.coarse_node: Any = None  # the whole map's first look, until the scans' own nodes arrive

    def load(self) -> None:
        view = self.view
        try:
            session = view.state.session
            levels = session_levels(
                session,
                lambda: view.state.sequence(lambda d, t: self._progress("Reading scans", d, t)).scans,
                lambda done: self._progress("Levels of detail", done, len(view.state.sequence())),
            )
            self.scans.total_points = levels.total_points
            # scans picked for editing are shown in full
            self.detail = DetailStream(view, self.scans, self.colouring, levels, lambda: self.colouring.selected.keys())
            budget = int(session.config.engine.get("display_budget", display.DEFAULT_BUDGET))
            view.controls.budget.value = budget  # type: ignore[misc]
            poses = session.poses()
            lo = np.min([p[:3, 3] for p in poses], axis=0)
            hi = np.max([p[:3, 3] for p in poses], axis=0)
            centre = (lo + hi) / 2
            size = max(float(np.linalg.norm(hi - lo)), 20.0)
            view.server.initial_camera.look_at = centre
            view.server.initial_camera.position = centre + np.array([-0.4, -0.6, 0.7]) * size
            self.rebuild_scans()
            self.detail.follow()
            view.controls.progress.visible = False
        except Exception as exc:
            view.error = str(exc)
            view.controls.status.content = f"**Cannot load this session:** {exc}"
            view.controls.progress.visible = False
            if not isinstance(exc, Slam6dError):
                traceback.print_exc()
        finally:
            view.ready.set()

    def _progress(self, stage: str, done: int, total: int) -> None:
        self.view.controls.progress.value = 100.0 * done / max(total, 1)  # type: ignore[misc]
        self.view.controls.status.content = f"{stage}… {done}/{total}"

    def rebuild_scans(self) -> None:
        """(Re)send every scan at the levels of detail the camera calls for within the budget
        (:mod:`app.view.detail_stream`): the only time every scan's points go over the wire.

        On the first pass, when the budget is above :data:`display.FIRST_LOOK_BUDGET`, the whole map
        first goes within that budget as *one* point cloud in world coordinates
        (:meth:`DetailStream.first_look`), so it is on screen after one message and one
        cheap frame (without a GPU a frame costs ~2 µs per point; and each scene node costs the
        server ~2 ms to make, seconds for a thousand scans). The scans' own nodes at the full budget
        replace it in one atomic batch, so a browser draws the map once per pass, complete, rather
        than redrawing a growing map after each scan.
        """
        view, scans, detail = self.view, self.scans, self.detail
        assert detail is not None
        budget = int(view.controls.budget.value)
        self.coarse_points = 0
        first = not scans.nodes
        if first and budget > display.FIRST_LOOK_BUDGET and detail.total_points > display.FIRST_LOOK_BUDGET:
            poses = view.state.session.poses()
            points, colours, centre = detail.first_look(display.FIRST_LOOK_BUDGET, poses)
            self.coarse_node = view.server.scene.add_point_cloud(
                "/coarse_map",
                points,
                colours,
                point_size=float(view.controls.point_size.value),
                point_shading="flat",
                # half the bytes of float32; relative to the map's centre a km-scale map quantises to
                # 0.5-1 m between 0.5 and 2 km from it, under a pixel of a view that shows all of it
                precision="float16",
                position=centre,
            )
            coarse_sent = time.monotonic()
            self.coarse_points = len(points)
            view.controls.status.content = (
                f"**{view.state.session.name}** · {len(poses)} scans · coarse view "
                f"({self.coarse_points:,} points), loading full detail…"
            )
            self._let_browsers_draw_coarse(coarse_sent)
        if first:
            self.before_full_pass()
        self._show_levels(detail.choose(budget, view.state.session.poses()), replace=True)
        self.draw_graph()
        show_status(view, scans)

    def _let_browsers_draw_coarse(self, sent: float) -> None:
        """Hold the full pass until the browser has the coarse one in a batch of its own.

        The viewer starts on the request for the session page, typically before that page's 3D
        view connects; a browser connecting after both passes were sent would get only the full
        one and draw nothing for seconds. Nobody connecting within :data:`_CLIENT_WAIT` means
        nobody is waiting for a first look.
        """
        if not self.client_seen.wait(max(0.0, sent + _CLIENT_WAIT - time.monotonic())):
            return
        time.sleep(_COARSE_SETTLE)

    def _show_levels(self, levels: list[int], replace: bool) -> None:
        """Display each scan at its level; ``replace`` drops the old nodes (and their poses) first.

        Without ``replace`` the scans keep the poses they are shown at, which may have moved
        (ICP stepping) since the previous pass was sent.
        """
        scans, detail = self.scans, self.detail
        assert detail is not None
        with self.view.lock:
            scans.local = detail.read(levels)
            detail.shown = list(levels)
            if replace or len(scans.poses) != len(scans.local):
                scans.poses = [p.copy() for p in self.view.state.session.poses()]
                scans.pose_version += 1
            self.colouring.scans_replaced()
            self._send_scans(detail.levels.names, replace)
            self.shown_revision = self.view.state.session.revision

    def _send_scans(self, names: list[str], replace: bool = True) -> None:
        """All scans in one atomic batch, so a browser never draws a scan half-replaced.

        A node added under an existing name takes the old one's place in the same batch, so a
        second pass never leaves a frame with a scan missing.

        Missing upstream (viser 1.1.1): a batch reaches the browser in websocket messages of at
        most 128 scene messages (``AsyncMessageBuffer.max_window_size``, with no public setting),
        about 4 per scan, and the browser redraws after each; a map of more than ~30 scans can
        therefore show its first pass in two or three steps. (Hiding the scans until all are sent
        does not work either: viser drops a queued "hidden" when "shown" follows.)
        """
        scans = self.scans
        with self.view.server.atomic():
            if self.coarse_node is not None:  # the first look at the whole map gives way to the scans
                self.coarse_node.remove()
                self.coarse_node = None
            if replace:
                for node in scans.nodes:
                    node.remove()
            for node, _ in scans.light.values():
                node.remove()
            scans.nodes, scans.light = [], {}
            for k, points in enumerate(scans.local):
                scans.nodes.append(
                    send_cloud(
                        self.view,
                        f"/scans/{names[k] or k}",
                        points,
                        self.colouring.scan_colours(k),
                        scans.poses[k],
                        precision=display.precision_for(points),
                        visible=scans.focus is None or k in scans.focus,
                    )
                )
            if scans.focus is not None:
                self.show_focus(scans.focus)

    def set_point_size(self) -> None:
        size = float(self.view.controls.point_size.value)
        for node in [*self.scans.nodes, *(light for light, _ in self.scans.light.values())]:
            node.point_size = size

    def set_poses(self, poses: list[Matrix], indices: list[int] | None = None) -> None:
        """Move scan nodes: only position and orientation of the nodes that moved are sent.

        One atomic batch, so a browser never draws a scan at a new position with its old rotation.
        """
        scans = self.scans
        with self.view.lock, self.view.server.atomic():
            if self.view.stopped:  # a stepper or replay thread may still be mid-step when the view stops
                return
            moved = False
            for k in range(len(poses)) if indices is None else indices:
                pose = np.asarray(poses[k], dtype=np.float64)
                if k >= len(scans.nodes) or np.array_equal(pose, scans.poses[k]):
                    continue
                scans.poses[k] = pose.copy()
                place(scans.nodes[k], pose)
                if k in scans.light and scans.focus is not None and k not in scans.focus:
                    place(scans.light[k][0], pose)  # a hidden light node is placed when shown
                moved = True
            self.pose_updates += 1
            if moved:
                self.colouring.scans_moved()
                scans.pose_version += 1
