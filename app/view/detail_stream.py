"""Levels of detail that follow the camera: the scans near it refined, far ones coarsened, within the budget.

The scans' levels are prefixes of a progressive store on disk (:mod:`slam6d.scan_levels`), so a
scan changing level costs one file read and one point-cloud message; the choice itself
(:func:`app.view.detail_levels.choose_levels`) looks at one distance per scan, not at points.

Every browser's camera reports its moves; the view is one scene shared by all browsers on the
session, so the levels follow the camera that moved last. Moves are debounced: while a camera is
dragged nothing is sent (a software renderer would spend the drag redrawing changing clouds), and
:data:`SETTLE` after it stops the scans whose level changed are sent again, in one atomic batch.
Scans picked for editing are shown in full resolution, so the points a person works on are all
there. While registration is being played back the map stays as it is (playback has its own light
copies of the shown scans).
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable, Collection, Sequence
from typing import Any

import numpy as np
import viser

from app.view import display
from app.view.colouring import Colouring
from app.view.core import ShownScans, ViewContext, send_cloud, show_status
from app.view.detail_levels import choose_levels, points_at
from slam6d.geometry import Matrix
from slam6d.scan_levels import ScanLevels

SETTLE = 0.3  # s without a camera move before the levels are chosen again
_POLL = 0.5  # s: how often picked scans are checked for (picking changes no camera)


class DetailStream:
    """The level each scan is shown at, and the thread that changes them as cameras move (module docstring)."""

    def __init__(
        self,
        view: ViewContext,
        scans: ShownScans,
        colouring: Colouring,
        levels: ScanLevels,
        full: Callable[[], Collection[int]],
    ) -> None:
        self.view = view
        self.scans = scans
        self.colouring = colouring
        self.levels = levels
        self.full = full  # scans to show in full resolution (picked for editing)
        self.shown: list[int] = []  # level per scan, as last sent
        self.camera: np.ndarray | None = None  # the position of the camera that moved last
        self.updates = 0  # passes of the follower that sent scans (tests and benchmarks watch it)
        self._moved = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def total_points(self) -> int:
        return self.levels.total_points

    def camera_position(self) -> np.ndarray:
        """The camera the levels follow: the last one moved, else where every browser starts."""
        if self.camera is not None:
            return self.camera
        return np.asarray(self.view.server.initial_camera.position, dtype=np.float64)

    def choose(self, budget: int, poses: Sequence[Matrix]) -> list[int]:
        """Levels for ``budget`` points at ``poses``, by distance from :meth:`camera_position`."""
        positions = np.array([p[:3, 3] for p in poses], dtype=np.float64).reshape(-1, 3)
        distances = np.linalg.norm(positions - self.camera_position(), axis=1)
        return choose_levels(self.levels.level_points, distances, budget, set(self.full()))

    def read(self, levels: Sequence[int]) -> list[np.ndarray]:
        """Each scan's points at its level (float32, own frame)."""
        return self.levels.at_levels(levels)

    def first_look(self, budget: int, poses: Sequence[Matrix]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every scan in one cloud of at most ``budget`` points, each in its scan colour: (points relative
        to the map's centre, float32; colours, uint8; that centre). One message and one scene node for
        the whole map.

        The scans get the levels :meth:`choose` gives for ``budget``; when even their coarsest levels are
        over it (1,000 scans x 128 points), every scan gets an equal share as a prefix of its progressive
        order (an even sample of the scan, :meth:`ScanLevels.samples`).
        """
        centre = np.mean([p[:3, 3] for p in poses], axis=0)
        counts = [self.levels.level_points[k][level] for k, level in enumerate(self.choose(budget, poses))]
        if sum(counts) > budget:
            share = max(budget // max(len(counts), 1), 1)
            counts = [min(count, share) for count in counts]
        clouds = self.levels.samples(counts)
        world = [
            c @ p[:3, :3].T.astype(np.float32) + (p[:3, 3] - centre).astype(np.float32)
            for c, p in zip(clouds, poses, strict=True)
        ]
        colours = [
            np.broadcast_to(np.array(display.scan_color(k), np.uint8), (len(c), 3)) for k, c in enumerate(clouds)
        ]
        return np.concatenate(world).astype(np.float32), np.concatenate(colours), centre

    def points_shown(self, levels: Sequence[int]) -> int:
        return points_at(self.levels.level_points, levels)

    # -------------------------------------------------------------- following the cameras

    def follow(self) -> None:
        """Listen to every browser's camera and start the thread that refines the map after a move."""
        self.view.server.on_client_connect(self._listen)
        self._thread = threading.Thread(target=self._run, name="viewer-detail", daemon=True)
        self._thread.start()

    def _listen(self, client: viser.ClientHandle) -> None:
        client.camera.on_update(self._camera_moved)

    def _camera_moved(self, camera: viser.CameraHandle) -> None:
        self.camera = np.asarray(camera.position, dtype=np.float64)
        self._moved.set()

    def _run(self) -> None:
        view = self.view
        while not view.stopped:
            if self._moved.wait(_POLL):
                # debounce: wait until the camera has been still for SETTLE
                while not view.stopped and self._moved.wait(SETTLE):
                    self._moved.clear()
            try:
                self.refresh()
            except Exception:  # the follower must outlive one bad pass (e.g. a store replaced underfoot)
                traceback.print_exc()

    def refresh(self) -> None:
        """Choose the levels again and send the scans whose level changed."""
        view = self.view
        if self.scans.focus is not None or not view.ready.is_set() or view.error or not self.shown:
            return
        with view.lock:
            if view.stopped:
                return
            levels = self.choose(int(view.controls.budget.value), self.scans.poses)
            changed = [k for k, level in enumerate(levels) if level != self.shown[k]]
            if changed:
                self.resend(changed, levels)

    def resend(self, scans: Sequence[int], levels: Sequence[int]) -> None:
        """Send ``scans`` again at ``levels`` (one atomic batch); their nodes are replaced in place."""
        view, shown, colouring = self.view, self.scans, self.colouring
        residual = view.controls.colour.value == "residual" and colouring.residuals is not None
        colouring.scans_moved()  # per shown point: the changed scans' residuals no longer match
        with view.server.atomic():
            for k in scans:
                shown.local[k] = self.levels.points(k, levels[k])
                self.shown[k] = levels[k]
                if k in shown.light:  # playback's light copy indexes the old points
                    shown.light.pop(k)[0].remove()
                name = shown.nodes[k].name
                shown.nodes[k] = send_cloud(
                    view,
                    name,
                    shown.local[k],
                    colouring.scan_colours(k),
                    shown.poses[k],
                    precision=display.precision_for(shown.local[k]),
                )
        self.updates += 1
        if residual:
            colouring.recolour()
        show_status(view, shown)

    def as_dict(self) -> dict[str, Any]:
        return {
            "levels": list(self.shown),
            "updates": self.updates,
            "camera": None if self.camera is None else self.camera.tolist(),
        }
