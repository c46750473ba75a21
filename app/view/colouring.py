"""Colouring the scans: by scan, height, residual or connected component, with scans picked for editing and highlighted pairs on top.

A single colour goes to the browser as one RGB triple, not one per point; only scans whose colour
changes are resent.
"""

from __future__ import annotations

import numpy as np

from app.view import display
from app.view.core import Colour, ViewCore
from app.view.playback import light_colours


class Colouring(ViewCore):
    highlight: dict[int, Colour]  # scans a panel marks (the pair being matched, displacement colours)
    selected: dict[int, Colour]  # scans picked for editing; drawn over highlight
    component_of: dict[int, int]  # scan -> connected component (app.view.panels.components fills it)

    def init_colouring(self) -> None:
        self.residuals = None
        self.highlight = {}
        self.selected = {}
        self.component_of = {}
        self.height_range = (0.0, 1.0)

    def scan_colours(self, k: int) -> np.ndarray | tuple[int, int, int]:
        if k in self.selected:
            return self.selected[k]
        if k in self.highlight:
            return self.highlight[k]
        mode = self.controls.colour.value
        if mode == "height":
            low, high = self.height_range
            return display.ramp(display.world_heights(self.local[k], self.poses[k]), low, high)
        if mode == "residual" and self.residuals is not None:
            return display.ramp(self.residuals[k], 0.0, 0.3)
        if mode == "component":
            return display.scan_color(self.component_of.get(k, 0))
        return display.scan_color(k)

    def recolour(self) -> None:
        with self.lock:
            if self.controls.colour.value == "height":
                self.height_range = display.height_range(self.local, self.poses)
            if self.controls.colour.value == "residual" and self.residuals is None:
                self.controls.status.content = "Computing residuals…"
                self.residuals = display.residuals(self.local, self.poses)
            with self.server.atomic():
                for k in range(len(self.nodes)):
                    self.paint(k)
        self.update_status()

    def paint(self, k: int) -> None:
        """Send scan ``k``'s colours; a single colour goes as one RGB triple, not one per point."""
        colours = np.asarray(self.scan_colours(k), np.uint8)
        self.nodes[k].colors = colours
        if k in self.light:
            node, keep = self.light[k]
            node.colors = light_colours(colours, keep)

    def select(self, selected: dict[int, tuple[int, int, int]]) -> None:
        """Mark scans picked for editing in their own colour; only scans whose colour changes are resent."""
        with self.lock, self.server.atomic():
            changed = set(self.selected) ^ set(selected) | {k for k in selected if self.selected.get(k) != selected[k]}
            self.selected = dict(selected)
            for k in changed:
                if k < len(self.nodes):
                    self.paint(k)
