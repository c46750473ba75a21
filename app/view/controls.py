"""The 3D view's own controls: the View, Registration and History folders, and the status lines above them.

Only the handles live here (built once per view, shared by every browser, like everything in a
viser scene); what a control does is wired up by :class:`app.view.session_view.SessionViewer`.
"""

from __future__ import annotations

import numpy as np
import viser

from app.view import display

NO_CHOICE = "—"  # a panel's dropdown entry while there is nothing to choose
COLOUR_MODES = ("scan", "height", "residual", "component")  # component: app.view.panels.components


class ViewControls:
    def __init__(self, gui: viser.GuiApi) -> None:
        self.status = gui.add_markdown("Loading scans…")
        self.warnings = gui.add_markdown("")
        self.progress = gui.add_progress_bar(0.0, animated=True)
        with gui.add_folder("View"):
            self.colour = gui.add_dropdown("Colour by", COLOUR_MODES, initial_value="scan")
            self.point_size = gui.add_slider("Point size", 0.005, 0.2, 0.005, 0.03)
            self.budget = gui.add_number(
                "Point budget", display.DEFAULT_BUDGET, min=10_000, max=20_000_000, step=10_000
            )
            self.apply_budget = gui.add_button("Apply budget")
            self.show_trajectory = gui.add_checkbox("Trajectory", True)
            self.show_edges = gui.add_checkbox("Graph edges", True)
            self.edge_legend = gui.add_markdown("")
        with gui.add_folder("Registration"):
            self.run_button = gui.add_button("Run registration")
            self.cancel_button = gui.add_button("Cancel job", disabled=True)
            self.step_button = gui.add_button("Step ICP iteration")
            self.next_scan_button = gui.add_button("Next scan")
            self.play_button = gui.add_button("Play")
            self.pause_button = gui.add_button("Pause", disabled=True)
            self.step_status = gui.add_markdown("")
            self.plot = gui.add_uplot(
                (np.zeros(0), np.zeros(0), np.zeros(0)),
                (
                    {"label": "iteration"},
                    {"label": "RMS (m)", "stroke": "#e8590c", "scale": "m"},
                    {"label": "pairs", "stroke": "#1c7ed6", "scale": "n"},
                ),
                title="ICP per iteration",
                scales={"x": {"time": False}, "m": {"auto": True}, "n": {"auto": True}},
                axes=({}, {"scale": "m"}, {"scale": "n", "side": 1}),
                aspect=1.6,
            )
        with gui.add_folder("History"):
            self.revision_text = gui.add_markdown("")
            self.undo_button = gui.add_button("Undo")
            self.redo_button = gui.add_button("Redo")

    def show_icp_history(self, history: list[tuple[int, float, int]]) -> None:
        """The "ICP per iteration" plot: (iteration, RMS, pairs) of the scan being matched."""
        h = np.array(history, dtype=np.float64).reshape(-1, 3)
        self.plot.data = (h[:, 0], h[:, 1], h[:, 2])
