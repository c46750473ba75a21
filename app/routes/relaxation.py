"""REST for relaxation and its measures: start a relaxation, the residuals of a revision, how far scans moved.

A graph that cannot be relaxed (scans not tied to a fixed scan, no fixed scan) is refused up front
with 409 and the reason; otherwise the relaxation is a job (202), polled at ``GET /api/jobs/{id}``.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query
from pydantic import Field

from app.routes.dependencies import REQUIRE_SESSION, ActorDep, EditorDep, SessionDep
from app.validation import MAX_INDEX, Index, RequestBody, RevisionQuery
from slam6d.residuals import displacements

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["relaxation"], dependencies=[REQUIRE_SESSION])


class RelaxRequest(RequestBody):
    method: str = Field(
        "lum",
        description="'lum' (joint point-to-plane over overlapping scans, slam6d run's default), "
        "'graph' (ICP per edge of the session's graph, then a pose-graph solve) or 'simultaneous'",
    )
    fixed: list[Index] = Field(default_factory=lambda: [0], max_length=100_000, description="scans held in place")


@router.post("/relax", status_code=202)
def relax(session_id: str, editor: EditorDep, actor: ActorDep, body: RelaxRequest | None = None) -> dict[str, Any]:
    """Global relaxation (a job); 409 with the reason when the graph is disconnected or nothing is fixed."""
    body = body or RelaxRequest()
    return actor.start_job(
        "relax", editor.relaxation.relax_job(session_id, actor.author, body.method, body.fixed), body.model_dump()
    )


@router.get("/residuals")
def residuals(session_id: str, state: SessionDep, editor: EditorDep, rev: RevisionQuery = None) -> dict[str, Any]:
    """Closest-point RMS and paired fraction over the graph's edges (the guardrail's measure)."""
    revision = state.session.get_revision(rev)
    return editor.context.residuals(session_id, revision.poses, revision.graph).as_dict()


@router.get("/displacement")
def displacement(
    state: SessionDep, before: Annotated[int, Query(ge=0, le=MAX_INDEX)], after: RevisionQuery = None
) -> dict[str, Any]:
    """Per-scan distance (m) each scan moved between two revisions (default: to the current one)."""
    a, b = state.session.get_revision(before), state.session.get_revision(after)
    return {"before": a.number, "after": b.number, "displacement": displacements(a.poses, b.poses)}
