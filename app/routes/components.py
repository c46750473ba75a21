"""REST for the connected components a relaxation would see, and the failed run the revision came from.

A viewer's read (like the residuals beside it): the 3D view colours the same components and shows
the same guardrail message.
"""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter

from app.editing.components import session_components
from app.routes.dependencies import REQUIRE_SESSION, EditorDep

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["relaxation"], dependencies=[REQUIRE_SESSION])


@router.get("/components")
def components(
    session_id: str, editor: EditorDep, method: Literal["lum", "graph", "simultaneous"] = "lum"
) -> dict[str, Any]:
    """The head revision's connected components under relaxation ``method`` (its graph: ``graph`` the session's
    edges, ``lum``/``simultaneous`` the overlapping pairs plus the sequential links), the last failed run
    it descends from, and the guardrail message; one component means relaxation can tie every scan together."""
    return session_components(editor.context, session_id, method)
