"""Folders of the 3D view's control panel beyond viewing and registration.

Each panel is thin: it turns buttons into calls of :mod:`app.editing` (the same calls the REST API
makes) and draws what comes back. Panels are rebuilt from the journal on every revision change
(``refresh``), so every browser on a session shows the same lists.
"""

from __future__ import annotations

import threading
from typing import Protocol

from app.view.panels.host import ViewerHost


class Panel(Protocol):
    def refresh(self) -> None: ...


def build_panels(viewer: ViewerHost) -> list[Panel]:
    from app.view.panels.components import ComponentsPanel
    from app.view.panels.edges import EdgesPanel
    from app.view.panels.guesses import GuessPanel
    from app.view.panels.loops import LoopsPanel
    from app.view.panels.replay import ReplayPanel

    loops = LoopsPanel(viewer)
    panels: list[Panel] = [loops, EdgesPanel(viewer), GuessPanel(viewer), ReplayPanel(viewer)]
    panels.append(ComponentsPanel(viewer, loops.method))  # the pieces the chosen relaxation would see

    def first_fill() -> None:  # lists need the scans' poses, which load in the background
        viewer.ready.wait()
        with viewer.lock:  # a view stopped while this thread waited draws nothing
            if not viewer.error:
                for panel in panels:
                    viewer.run_safely(panel.refresh)

    threading.Thread(target=first_fill, name=f"panels-{viewer.session_id}", daemon=True).start()
    return panels
