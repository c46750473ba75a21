"""Editing a session's map after a run, by hand and by stage; one module per concern.

* :mod:`app.editing.loops` - the loop hypotheses to review: detect, list, accept, reject.
* :mod:`app.editing.edges` - the graph by hand: add an ICP-refined edge, delete one, move a scan.
* :mod:`app.editing.relaxation` - loop closing and relaxation jobs.
* :mod:`app.editing.guesses` - octree guesses for a pair, ICP from a chosen candidate.
* :mod:`app.editing.context` - what they share: settings, reduced scans, residual-checked commits.
* :mod:`slam6d.session_graph` (engine) - the pose-graph document a revision stores.

The REST routes (:mod:`app.routes`) and the 3D view's panels both call one :class:`Editor` per
workbench, so a button and a request do the same thing, and every change is one journal entry
(with author and parameters) that undo/redo and every other browser on the session see.
"""

from __future__ import annotations

from app.editing.context import EditContext
from app.editing.edges import GraphEdits
from app.editing.guesses import OctreeGuesses
from app.editing.loops import LoopReview
from app.editing.relaxation import Relaxation
from app.per_owner import PerOwner
from app.workbench import Workbench


class Editor:
    """Every kind of edit of one workbench's sessions, sharing one :class:`EditContext` (and its scan cache)."""

    def __init__(self, workbench: Workbench) -> None:
        self.context = EditContext(workbench)
        self.loops = LoopReview(self.context)
        self.edges = GraphEdits(self.context)
        self.relaxation = Relaxation(self.context)
        self.guesses = OctreeGuesses(self.context)


editor_for: PerOwner[Workbench, Editor] = PerOwner(Editor)
"""The one editor of a workbench (shared by the REST API and the 3D views)."""


__all__ = ["Editor", "editor_for"]
