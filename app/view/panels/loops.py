"""Loops and relaxation: the hypothesis review list, loop closing and relaxation jobs, before/after."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.editing import editor_for
from app.permalink import Selection
from app.view import display
from app.view.controls import NO_CHOICE
from app.view.panels.host import ViewerHost
from app.view.panels.paging import Pager
from app.view.selection_marker import marker_of
from slam6d.relaxation_methods import RELAXATION_METHODS
from slam6d.residuals import displacements


class LoopsPanel:
    def __init__(self, viewer: ViewerHost) -> None:
        self.viewer = viewer
        self.editor = editor_for(viewer.workbench)
        self.session_id = viewer.session_id
        gui = viewer.server.gui
        with gui.add_folder("Loops & relaxation", expand_by_default=False):
            self.detect = gui.add_button("Detect loops")
            self.table = gui.add_markdown("No loop hypotheses yet.")
            self.pages = Pager(gui, "Hypotheses page", lambda: viewer.run_safely(self.refresh))
            self.choice = gui.add_dropdown("Hypothesis", [NO_CHOICE])
            self.choices: dict[str, Selection] = {}  # the options -> the hypotheses they name
            self.accept = gui.add_button("Accept loop")
            self.reject = gui.add_button("Reject loop")
            self.close = gui.add_button("Close loops (error diffusion)")
            self.method = gui.add_dropdown("Relaxation", RELAXATION_METHODS, initial_value="lum")
            self.relax = gui.add_button("Relax")
            self.before = gui.add_checkbox("Show before (parent revision)", False)
            self.by_displacement = gui.add_checkbox("Colour by displacement", False)
            self.legend = gui.add_markdown("")
        run = viewer.run_safely
        self.detect.on_click(lambda e: run(lambda: self._submit("detect-loops", self.editor.loops.detect_job, e)))
        self.accept.on_click(lambda e: run(lambda: self._decide(True, e)))
        self.reject.on_click(lambda e: run(lambda: self._decide(False, e)))
        self.close.on_click(
            lambda e: run(lambda: self._submit("close-loops", self.editor.relaxation.close_loops_job, e))
        )
        self.relax.on_click(lambda e: run(lambda: self._relax(e)))
        self.choice.on_update(lambda e: run(lambda: self._chosen(e)))
        self.before.on_update(lambda _: run(self._show_before))
        self.by_displacement.on_update(lambda _: run(self._colour))

    def _submit(self, kind: str, make: Any, event: Any, **extra: Any) -> None:
        author = self.viewer.author(event)
        work = make(self.session_id, author, **extra)
        self.viewer.workbench.jobs.submit(self.session_id, kind, work, author, extra)

    def _relax(self, event: Any) -> None:
        # relax_job refuses before any job starts what cannot run (no fixed scan; for graph, a disconnected graph)
        self._submit("relax", self.editor.relaxation.relax_job, event, method=self.method.value, fixed=[0])

    def _decide(self, accept: bool, event: Any) -> None:
        if self.choice.value == NO_CHOICE:
            raise ValueError("choose a loop hypothesis first")
        k = int(self.choice.value.split(":")[0])
        self.editor.loops.decide(self.session_id, k, accept, self.viewer.author(event))

    def _chosen(self, event: Any) -> None:
        """A hypothesis chosen by a person (not by a refresh) is that browser's selection too."""
        chosen = self.choices.get(self.choice.value)
        if event.client is not None and chosen is not None:
            marker_of(event.client).picked(chosen)

    def refresh(self) -> None:
        listed = self.editor.loops.listed(self.session_id)
        if not listed:
            self.table.content = "No loop hypotheses yet: run registration or *Detect loops*."
            self.choice.options = [NO_CHOICE]
        else:
            listed, caption = self.pages.page(listed, "hypotheses")
            rows = [
                f"| {h['k']} | {h['i']}–{h['j']} | {h['distance']:.2f} | {h['overlap']:.2f} | {h['fitness']:.2f} "
                f"| {'✔' if h['verified'] else '✘ ' + h['reason']} | **{h['status']}** |"
                for h in listed
            ]
            header = (
                "| # | scans | dist (m) | overlap | ICP fitness | verified | status |\n|---|---|---|---|---|---|---|"
            )
            self.table.content = header + "\n" + "\n".join(rows) + (f"\n\n{caption}" if caption else "")
            self.choices = {
                f"{h['k']}: scans {h['i']}–{h['j']} ({h['status']})": Selection.pair("loop", h["i"], h["j"])
                for h in listed
            }
            options = list(self.choices)
            previous = self.choice.value.split(":")[0]
            self.choice.options = options
            self.choice.value = next((o for o in options if o.split(":")[0] == previous), options[0])  # type: ignore[misc]
        if self.before.value or self.by_displacement.value:
            self._show_before()
            self._colour()

    def _revisions(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        session = self.viewer.state.session
        current = session.get_revision()
        parent = session.get_revision(current.parent) if current.parent is not None else current
        return parent.poses, current.poses

    def _show_before(self) -> None:
        before, after = self._revisions()
        self.viewer.set_poses(before if self.before.value else after)
        self.viewer.graph.draw()

    def _colour(self) -> None:
        viewer = self.viewer
        if not self.by_displacement.value:
            viewer.colouring.highlight = {}
            self.legend.content = ""
        else:
            moved = np.array(displacements(*self._revisions()))
            top = float(moved.max()) if len(moved) and moved.max() > 0 else 1.0
            colours = display.ramp(moved, 0.0, top)
            viewer.colouring.highlight = {k: display.rgb(colours[k]) for k in range(len(moved))}
            self.legend.content = f"Displacement since the parent revision: blue 0 m → red {top:.2f} m"
        viewer.colouring.recolour()
