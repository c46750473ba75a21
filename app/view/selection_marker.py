"""The selected scan, edge or loop hypothesis, marked in one browser's own scene, and what it picked in the 3D view.

A selection belongs to the person looking (a permalink carries it to a teammate), not to the
session: the marker is added to that browser's scene only (``client.scene``), so others on the same
3D view see nothing of it. A scan is outlined by its box (the displayed points' bounds, in the
scan's own frame, placed at its pose), an edge or loop by a thick line between the two scans, each
with a label.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from app.per_owner import PerOwner
from slam6d.geometry import Matrix, rotation_to_quaternion

MARKER_COLOUR = (255, 230, 40)  # bright yellow: stands out against every colour mode's ramp
NAME = "/selection"


def box_segments(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The 12 edges of the axis-aligned box ``low``-``high`` as (12, 2, 3) segments."""
    corners = np.array(list(itertools.product(*zip(low, high, strict=True))), dtype=np.float32)
    pairs = [(a, b) for a, b in itertools.combinations(range(8), 2) if bin(a ^ b).count("1") == 1]
    return np.array([[corners[a], corners[b]] for a, b in pairs], dtype=np.float32)


class SelectionMarker:
    """The marker of one browser's selection (``client`` is its viser ClientHandle)."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.handles: list[Any] = []
        self.picks = 0  # how many times something was picked in the 3D view itself (the page polls it)
        self.last_pick: Any = None  # the latest of them (an app.permalink.Selection)

    def picked(self, selection: Any) -> None:
        """The browser picked ``selection`` in the 3D view itself (a click on a scan, an edge or a loop
        hypothesis chosen in a panel). Only recorded here: the browser's page, which polls it, makes it
        the page's selection - marked through :meth:`show`, described and put in the address - like one
        made in the page. Counting the picks lets the page tell a new pick from an old one."""
        self.last_pick = selection
        self.picks += 1

    def show(
        self, selection: Any, poses: Sequence[Matrix], bounds: Callable[[int], tuple[np.ndarray, np.ndarray]]
    ) -> None:
        """Mark ``selection`` (an :class:`app.permalink.Selection`; None clears) at ``poses``.

        ``bounds(k)`` is scan k's (low, high) corners in its own frame."""
        scene = self.client.scene
        with self.client.atomic():
            for handle in self.handles:
                handle.remove()
            self.handles = []
            if selection is None:
                return
            if selection.kind == "scan":
                pose = poses[selection.i]
                low, high = bounds(selection.i)
                frame = scene.add_frame(NAME, show_axes=False, position=pose[:3, 3], wxyz=_wxyz(pose))
                self.handles.append(frame)
                scene.add_line_segments(
                    f"{NAME}/box",
                    box_segments(low, high),
                    colors=MARKER_COLOUR,
                    thickness=3.0,
                    thickness_units="screen",
                )
                scene.add_label(f"{NAME}/label", f"scan {selection.i}", position=tuple(float(v) for v in high))
                return
            a, b = (poses[k][:3, 3] for k in (selection.i, selection.j))
            frame = scene.add_frame(NAME, show_axes=False, position=a)
            self.handles.append(frame)
            scene.add_line_segments(
                f"{NAME}/line",
                np.array([[[0.0, 0.0, 0.0], b - a]], dtype=np.float32),
                colors=MARKER_COLOUR,
                thickness=8.0,
                thickness_units="screen",
            )
            scene.add_label(
                f"{NAME}/label", f"{selection.kind} {selection.i}–{selection.j}", position=tuple((b - a) / 2)
            )


def _wxyz(pose: Matrix) -> tuple[float, float, float, float]:
    w, x, y, z = (float(v) for v in rotation_to_quaternion(pose[:3, :3]))
    return w, x, y, z


marker_of: PerOwner[Any, SelectionMarker] = PerOwner(SelectionMarker)
"""The marker of a browser (a viser ClientHandle), made on its first selection, gone with the browser."""


__all__ = ["SelectionMarker", "box_segments", "marker_of"]
