"""Which pieces a session's relaxation would see: the connected components of its graph, and the last failed run.

A registration whose relaxation found the graph disconnected keeps its poses as a revision and
names the components in its journal entry (:meth:`app.registration.RunCommit.keep_partial`). The operator
then bridges them by hand (an edge between two picked scans, a dragged scan matched from there) and
relaxes again; this module answers, for the head revision, which components the chosen method's graph
has now (:func:`slam6d.relaxation_methods.relaxation_components`) and which failure the revision
descends from, so the 3D view and REST can show the guardrail until the pieces are one.
"""

from __future__ import annotations

from typing import Any

from app.editing.context import EditContext
from slam6d.posegraph import describe_components
from slam6d.relaxation_methods import relaxation_components
from slam6d.session import Session
from slam6d.session_graph import graph_edges, sequential_links


def session_components(context: EditContext, session_id: str, method: str = "lum") -> dict[str, Any]:
    """The head revision's connected components under relaxation ``method``, as ``GET .../components`` answers.

    ``components`` are scan indices (each sorted, ordered by their first scan); ``ranges`` writes
    them as ``[0-3]; [4-7]``; ``failure`` is the last failed run this revision descends from (or None)
    and ``message`` the guardrail sentence the view shows.
    """
    head = context.workbench.head(session_id)
    count = len(head.poses)
    components = relaxation_components(
        method,
        None if method == "graph" else context.models(session_id),  # graph needs no scan
        head.poses,
        graph_edges(count, head.graph),
        context.config(session_id).relax,
        sequential_links(count, head.graph),
    )
    failure = last_failure(context.session(session_id), head.number)
    ranges = describe_components(components, limit=len(components))
    if len(components) > 1:
        message = (
            f"{method} relaxation would find the graph disconnected: {len(components)} components {ranges}; "
            "bridge them (an edge between two picked scans, or drag a scan and run ICP from there) and relax again"
        )
    else:
        message = f"all {count} scans form one connected component for {method} relaxation"
    if failure is not None:
        message = (
            f"the {failure['stage']} stage failed (revision {failure['revision']}): {failure['reason']}. {message}"
        )
    return {
        "revision": head.number,
        "method": method,
        "count": len(components),
        "components": components,
        "ranges": ranges,
        "failure": failure,
        "message": message,
    }


def last_failure(session: Session, number: int) -> dict[str, Any] | None:
    """The failure recorded by the nearest revision at or above ``number`` in its ancestry that a failed
    run committed (stage, reason, the revision, the components then), or None. Ancestry, not journal
    order: after an undo past a failed run, a revision on another branch does not descend from it."""
    failed = {
        entry.revision: entry
        for entry in session.journal.entries()
        if entry.revision is not None and isinstance(entry.parameters.get("failure"), dict)
    }
    if not failed:  # the usual case: nothing to walk
        return None
    oldest = min(failed)
    current: int | None = number
    while current is not None and current >= oldest:  # a parent is always older (a smaller number)
        entry = failed.get(current)
        if entry is not None:
            failure = entry.parameters["failure"]
            return {
                "stage": failure.get("stage"),
                "reason": failure.get("reason"),
                "revision": current,
                "components": entry.parameters.get("components", []),
            }
        revision = session.journal.revision(current)
        current = None if revision is None else revision.parent
    return None
