"""REST for relaxation and its measures: start a relaxation, the residuals of a revision, how far scans moved.

A graph that cannot be relaxed (scans not tied to a fixed scan, no fixed scan) is refused up front
with 409 and the reason; otherwise the relaxation is a job (202), polled at ``GET /api/jobs/{id}``.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query
from pydantic import BaseModel, Field

from app.routes.dependencies import REQUIRE_SESSION, Author, EditorDep, SessionDep, WorkbenchDep
from slam6d.residuals import displacements

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["relaxation"], dependencies=[REQUIRE_SESSION])


class RelaxRequest(BaseModel):
    method: str = Field("lum", description="'lum' (over the session's graph) or 'simultaneous'")
    fixed: list[int] = Field(default_factory=lambda: [0], description="scans held in place")


@router.post("/relax", status_code=202)
def relax(
    session_id: str,
    editor: EditorDep,
    workbench: WorkbenchDep,
    body: RelaxRequest | None = None,
    author: Author = "anonymous",
) -> dict[str, Any]:
    """Global relaxation (a job); 409 with the reason when the graph is disconnected or nothing is fixed."""
    body = body or RelaxRequest()
    work = editor.relaxation.relax_job(session_id, author, body.method, body.fixed)
    return workbench.jobs.submit(session_id, "relax", work, author, body.model_dump()).as_dict()


@router.get("/residuals")
def residuals(
    session_id: str, state: SessionDep, editor: EditorDep, rev: Annotated[int | None, Query(ge=0)] = None
) -> dict[str, Any]:
    """Closest-point RMS and paired fraction over the graph's edges (the guardrail's measure)."""
    revision = state.session.get_revision(rev)
    return editor.context.residuals(session_id, revision.poses, revision.graph).as_dict()


@router.get("/displacement")
def displacement(
    state: SessionDep, before: Annotated[int, Query(ge=0)], after: Annotated[int | None, Query(ge=0)] = None
) -> dict[str, Any]:
    """Per-scan distance (m) each scan moved between two revisions (default: to the current one)."""
    a, b = state.session.get_revision(before), state.session.get_revision(after)
    return {"before": a.number, "after": b.number, "displacement": displacements(a.poses, b.poses)}
