"""Colouring the scans: by scan, height, residual or connected component, with scans picked for editing and highlighted pairs on top.

A single colour goes to the browser as one RGB triple, not one per point; only scans whose colour
changes are resent.
"""

from __future__ import annotations

import numpy as np

from app.view import display
from app.view.core import Colour, ShownScans, ViewContext, show_status


def light_colours(colours: np.ndarray | Colour, keep: np.ndarray) -> np.ndarray:
    """A scan's colours for its light node: those of the kept points, or the one colour of the scan."""
    array = np.asarray(colours, np.uint8)
    return array[keep] if array.ndim == 2 else array


class Colouring:
    def __init__(self, view: ViewContext, scans: ShownScans) -> None:
        self.view = view
        self.scans = scans
        self.highlight: dict[int, Colour] = {}  # scans a panel marks (the pair being matched, displacements)
        self.selected: dict[int, Colour] = {}  # scans picked for editing; drawn over highlight
        self.component_of: dict[int, int] = {}  # scan -> connected component (app.view.panels.components)
        self.residuals: list[np.ndarray] | None = None  # per-point residuals, None once the poses change
        self.height_range = (0.0, 1.0)  # the height colouring's scale

    def scans_moved(self) -> None:
        """The shown poses changed: the per-point residuals belong to the old ones."""
        self.residuals = None

    def scans_replaced(self) -> None:
        """New display points were chosen: rescale the height colouring, drop the old residuals."""
        self.residuals = None
        if self.view.controls.colour.value == "height":
            self.height_range = display.height_range(self.scans.local, self.scans.poses)

    def scan_colours(self, k: int) -> np.ndarray | Colour:
        if k in self.selected:
            return self.selected[k]
        if k in self.highlight:
            return self.highlight[k]
        mode = self.view.controls.colour.value
        if mode == "height":
            low, high = self.height_range
            return display.ramp(display.world_heights(self.scans.local[k], self.scans.poses[k]), low, high)
        if mode == "residual" and self.residuals is not None:
            return display.ramp(self.residuals[k], 0.0, 0.3)
        if mode == "component":
            return display.scan_color(self.component_of.get(k, 0))
        return display.scan_color(k)

    def recolour(self) -> None:
        scans = self.scans
        with self.view.lock:
            if self.view.controls.colour.value == "height":
                self.height_range = display.height_range(scans.local, scans.poses)
            if self.view.controls.colour.value == "residual" and self.residuals is None:
                self.view.controls.status.content = "Computing residuals…"
                self.residuals = display.residuals(scans.local, scans.poses)
            with self.view.server.atomic():
                for k in range(len(scans.nodes)):
                    self.paint(k)
        show_status(self.view, self.scans)  # after a recolouring that said "Computing…"

    def paint(self, k: int) -> None:
        """Send scan ``k``'s colours; a single colour goes as one RGB triple, not one per point."""
        colours = np.asarray(self.scan_colours(k), np.uint8)
        self.scans.nodes[k].colors = colours
        if k in self.scans.light:
            node, keep = self.scans.light[k]
            node.colors = light_colours(colours, keep)

    def set_highlight(self, highlight: dict[int, Colour]) -> None:
        """Mark scans in their own colour (the pair being matched, a replayed pair); only the scans
        whose marking changes are repainted."""
        with self.view.lock:
            changed = {*self.highlight, *highlight}
            self.highlight = dict(highlight)
            for k in changed:
                if k < len(self.scans.nodes):
                    self.paint(k)

    def select(self, selected: dict[int, Colour]) -> None:
        """Mark scans picked for editing in their own colour; only scans whose colour changes are resent."""
        with self.view.lock, self.view.server.atomic():
            changed = set(self.selected) ^ set(selected) | {k for k in selected if self.selected.get(k) != selected[k]}
            self.selected = dict(selected)
            for k in changed:
                if k < len(self.scans.nodes):
                    self.paint(k)
