"""The connected components a relaxation would see, in distinct colours, with the guardrail message.

After a registration whose relaxation found the graph disconnected (its poses kept as a revision)
or after an edit that cut the graph, the scans fall into pieces that relaxation cannot tie
together. This folder names them (as scan ranges, with the failed stage and its reason when the
revision descends from a failed run) for the method chosen under *Loops & relaxation*, and the
first time there is more than one it switches *Colour by* to ``component``: one colour per piece.
The operator bridges them with *Edit graph* (pick a scan in each piece and add an edge, or drag a
scan and run ICP from there) and relaxes again; the folder follows every revision.
"""

from __future__ import annotations

from typing import Any

from app.editing import editor_for
from app.editing.components import last_failure, session_components
from app.view.panels.host import ViewerHost


class ComponentsPanel:
    def __init__(self, viewer: ViewerHost, method: Any) -> None:
        """``method`` is the relaxation dropdown of the loops panel: the components of the graph it relaxes."""
        self.viewer = viewer
        self.editor = editor_for(viewer.workbench)
        self.method = method
        self.count: int | None = None  # components at the last refresh (None before the first)
        with viewer.server.gui.add_folder("Components", expand_by_default=True):
            self.message = viewer.server.gui.add_markdown("")
        method.on_update(lambda _: viewer.run_safely(self.refresh))
        colour = viewer.controls.colour
        colour.on_update(lambda _: self._colour_chosen())
        self.switching = False  # True while refresh itself turns the component colouring on

    def _colour_chosen(self) -> None:
        if self.viewer.controls.colour.value == "component" and not self.switching:
            self.viewer.run_safely(self.refresh)

    def refresh(self) -> None:
        viewer = self.viewer
        method = str(self.method.value)
        session_id = viewer.session_id
        # lum and simultaneous find their graph from the scans (reduced models, overlap counted): done
        # when someone looks (component colours) or a failed run left pieces, not on every view of a session
        wanted = (
            viewer.controls.colour.value == "component"
            or last_failure(viewer.state.session, viewer.state.session.revision) is not None
        )
        if method != "graph" and not wanted:
            viewer.colouring.component_of = {}
            self.count = None
            self.message.content = (
                f"Choose *Colour by* `component` to see the connected components {method} relaxation would find."
            )
            return
        found = session_components(self.editor.context, session_id, method)
        with viewer.lock:
            viewer.colouring.component_of = {k: n for n, group in enumerate(found["components"]) for k in group}
        count = int(found["count"])
        became_split = count > 1 and (self.count is None or self.count <= 1)
        self.count = count
        colour = viewer.controls.colour
        if became_split and colour.value != "component":
            self.switching = True
            try:
                colour.value = "component"  # type: ignore[misc]  # the view's own handler recolours
            finally:
                self.switching = False
        elif colour.value == "component":
            viewer.colouring.recolour()
        # last: once the message shows, the colours it speaks of are drawn
        self.message.content = f"**⚠ {found['message']}**" if count > 1 else found["message"]
