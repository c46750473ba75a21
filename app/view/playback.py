"""Playback while registration is stepped: the current pair drawn in full, the rest of the map light.

Without a GPU a frame costs about a microsecond or two per point, so with the whole budget on
screen a browser draws one pose in seconds and falls behind the stepping; with a light map it
keeps up. The light points are a subset of the displayed ones, sent once as nodes of their own next
to the full ones: switching is a visibility change, nothing is re-sent.
"""

from __future__ import annotations

import numpy as np

from app.view import display
from app.view.core import Colour, ViewCore, place


def light_colours(colours: np.ndarray | Colour, keep: np.ndarray) -> np.ndarray:
    """A scan's colours for its light node: those of the kept points, or the one colour of the scan."""
    array = np.asarray(colours, np.uint8)
    return array[keep] if array.ndim == 2 else array


class Playback(ViewCore):
    def init_playback(self) -> None:
        self.light = {}
        self.focus = None

    def begin_playback(self, focus: list[int]) -> None:
        """Stepping plays: draw ``focus`` (the current pair) in full and the rest of the map light.

        Without a GPU a frame costs about a microsecond or two per point, so with the whole budget
        on screen a browser draws one pose in seconds and falls behind the stepping; with the light
        map it keeps up. The light points are a subset of the displayed ones, sent once as nodes of
        their own next to the full ones: switching is a visibility change, nothing is re-sent.
        """
        self.show_focus(focus)

    def end_playback(self) -> None:
        """Back to the whole map at the full budget (the full nodes were kept, hidden)."""
        with self.lock, self.server.atomic():
            self.focus = None
            for k, node in enumerate(self.nodes):
                node.visible = True
                if k in self.light:
                    self.light[k][0].visible = False

    def show_focus(self, focus: list[int]) -> None:
        with self.lock, self.server.atomic():
            self.focus = list(focus)
            share = max(1, display.PLAYBACK_BUDGET // max(1, len(self.nodes)))
            for k, node in enumerate(self.nodes):
                full = k in self.focus
                node.visible = full
                if not full and k not in self.light:
                    keep = display.display_indices(self.local[k], 0.0, share)
                    pose = self.poses[k]
                    light = self.add_cloud(
                        f"/light/{k}",
                        self.local[k][keep],
                        light_colours(self.scan_colours(k), keep),
                        pose,
                        precision=display.precision_for(self.local[k]),  # the full scan's, so both nodes match
                    )
                    self.light[k] = (light, keep)
                if k in self.light:
                    if not full:
                        place(self.light[k][0], self.poses[k])
                    self.light[k][0].visible = not full
