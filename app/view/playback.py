"""Playback while registration is stepped: the current pair drawn in full, the rest of the map light.

Without a GPU a frame costs about a microsecond or two per point, so with the whole budget on
screen a browser draws one pose in seconds and falls behind the stepping; with a light map it
keeps up. The light points are a subset of the displayed ones, sent once as nodes of their own next
to the full ones: switching is a visibility change, nothing is re-sent.
"""

from __future__ import annotations

from app.view import display
from app.view.colouring import Colouring, light_colours
from app.view.core import ShownScans, ViewContext, place, send_cloud


class Playback:
    def __init__(self, view: ViewContext, scans: ShownScans, colouring: Colouring) -> None:
        self.view = view
        self.scans = scans
        self.colouring = colouring

    def begin(self, focus: list[int]) -> None:
        """Stepping plays: draw ``focus`` (the current pair) in full and the rest of the map light."""
        self.show_focus(focus)

    def end(self) -> None:
        """Back to the whole map at the full budget (the full nodes were kept, hidden)."""
        scans = self.scans
        with self.view.lock, self.view.server.atomic():
            scans.focus = None
            for k, node in enumerate(scans.nodes):
                node.visible = True
                if k in scans.light:
                    scans.light[k][0].visible = False

    def show_focus(self, focus: list[int]) -> None:
        """Show ``focus`` in full and every other scan by its light node (sent the first time it is needed)."""
        scans = self.scans
        with self.view.lock, self.view.server.atomic():
            scans.focus = list(focus)
            share = max(1, display.PLAYBACK_BUDGET // max(1, len(scans.nodes)))
            for k, node in enumerate(scans.nodes):
                full = k in scans.focus
                node.visible = full
                if not full and k not in scans.light:
                    keep = display.display_indices(scans.local[k], 0.0, share)
                    light = send_cloud(
                        self.view,
                        f"/light/{k}",
                        scans.local[k][keep],
                        light_colours(self.colouring.scan_colours(k), keep),
                        scans.poses[k],
                        precision=display.precision_for(scans.local[k]),  # the full scan's, so both nodes match
                    )
                    scans.light[k] = (light, keep)
                if k in scans.light:
                    if not full:
                        place(scans.light[k][0], scans.poses[k])
                    scans.light[k][0].visible = not full
