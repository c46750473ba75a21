"""REST for editing a session after a run: loops to review, edges, moves, loop closing, relaxation, guesses, traces.

Every call that changes poses or the graph answers with the new ``revision`` (undo/redo and the
other browsers follow from the journal). Long work (loop detection, loop closing, relaxation) is a
background job: 202 with the job, polled at ``GET /api/jobs/{id}``. A graph that cannot be relaxed
(scans not tied to a fixed scan, no fixed scan) is refused up front with 409 and the reason.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query
from pydantic import BaseModel, Field

from app import traces
from app.api import Author, _state
from app.editing import editor_for
from app.guard import requires
from app.jobs import JobConflictError, Work
from app.tokens import Role
from app.workbench import EditError, Workbench
from slam6d.errors import RelaxationError, Slam6dError


class EdgeRequest(BaseModel):
    i: int = Field(ge=0)
    j: int = Field(ge=0)
    force: bool = Field(False, description="store the edge even when ICP does not confirm the match")


class PoseRequest(BaseModel):
    pose: list[list[float]] = Field(description="4x4 world_from_scan, canonical frame (metres, z up)")
    refine: bool = Field(False, description="run ICP from this pose against the scan's graph neighbours")


class RelaxRequest(BaseModel):
    method: str = Field("lum", description="'lum' (over the session's graph) or 'simultaneous'")
    fixed: list[int] = Field(default_factory=lambda: [0], description="scans held in place")


class CandidateRequest(BaseModel):
    data: int = Field(ge=0)
    model: int | None = Field(None, ge=0)
    candidate: int = Field(0, ge=0, description="rank in the candidate list (0 = the search's winner)")
    level: int = -1


def build_edit_router(workbench: Workbench) -> APIRouter:
    router = APIRouter(prefix="/api/sessions/{session_id}", tags=["editing"])
    editor = editor_for(workbench)

    def call(session_id: str, action: Any) -> Any:
        _state(workbench, session_id)
        try:
            return action()
        except EditError as exc:
            raise HTTPException(exc.status, str(exc)) from None
        except RelaxationError as exc:
            raise HTTPException(409, str(exc)) from None
        except Slam6dError as exc:
            raise HTTPException(422, str(exc)) from None

    def submit(session_id: str, kind: str, make_work: Any, author: str, parameters: dict[str, Any]) -> dict:
        work: Work = call(session_id, make_work)
        try:
            return workbench.jobs.submit(session_id, kind, work, author, parameters).as_dict()
        except JobConflictError as exc:
            raise HTTPException(409, str(exc)) from None

    @router.get("/loops")
    def loops(session_id: str) -> list[dict[str, Any]]:
        """The latest loop hypotheses (scan pair, distance, overlap, ICP fitness) with their review status."""
        return call(session_id, lambda: editor.hypotheses(session_id))

    @router.post("/loops/detect", status_code=202)
    def detect_loops(session_id: str, author: Author = "anonymous") -> dict[str, Any]:
        """Find and verify loop hypotheses from the current poses (a job); the result is the review list."""
        return submit(session_id, "detect-loops", lambda: editor.detect_loops_job(session_id, author), author, {})

    @router.post("/loops/{k}/accept", openapi_extra=requires(Role.reviewer))
    def accept_loop(session_id: str, k: int, author: Author = "anonymous") -> dict[str, Any]:
        return call(session_id, lambda: editor.decide_loop(session_id, k, True, author))

    @router.post("/loops/{k}/reject", openapi_extra=requires(Role.reviewer))
    def reject_loop(session_id: str, k: int, author: Author = "anonymous") -> dict[str, Any]:
        return call(session_id, lambda: editor.decide_loop(session_id, k, False, author))

    @router.get("/edges")
    def edges(session_id: str) -> list[dict[str, Any]]:
        """The current pose graph's edges; ``k`` is what ``DELETE .../edges/{k}`` takes."""
        return call(session_id, lambda: editor.edges(session_id))

    @router.post("/edges", status_code=201)
    def add_edge(session_id: str, body: EdgeRequest, author: Author = "anonymous") -> dict[str, Any]:
        """A loop edge between scans i and j, refined by ICP (422 when they do not match, unless ``force``)."""
        return call(session_id, lambda: editor.add_edge(session_id, body.i, body.j, author, body.force))

    @router.delete("/edges/{k}")
    def delete_edge(session_id: str, k: int, author: Author = "anonymous") -> dict[str, Any]:
        return call(session_id, lambda: editor.delete_edge(session_id, k, author))

    @router.post("/scans/{k}/pose")
    def move_scan(session_id: str, k: int, body: PoseRequest, author: Author = "anonymous") -> dict[str, Any]:
        """Place a scan by hand (optionally ICP from there); answers the residuals before/after and any warning."""
        return call(session_id, lambda: editor.move_scan(session_id, k, body.pose, author, body.refine))  # type: ignore[arg-type]

    @router.post("/close-loops", status_code=202)
    def close_loops(session_id: str, author: Author = "anonymous") -> dict[str, Any]:
        """Error diffusion over the accepted loop and manual edges (a job)."""
        return submit(session_id, "close-loops", lambda: editor.close_loops_job(session_id, author), author, {})

    @router.post("/relax", status_code=202)
    def relax(session_id: str, body: RelaxRequest | None = None, author: Author = "anonymous") -> dict[str, Any]:
        """Global relaxation (a job); 409 with the reason when the graph is disconnected or nothing is fixed."""
        body = body or RelaxRequest()
        return submit(
            session_id,
            "relax",
            lambda: editor.relax_job(session_id, author, body.method, body.fixed),
            author,
            body.model_dump(),
        )

    @router.get("/residuals")
    def residuals(session_id: str, rev: Annotated[int | None, Query(ge=0)] = None) -> dict[str, Any]:
        """Closest-point RMS and paired fraction over the graph's edges (the guardrail's measure)."""

        def summary() -> dict[str, Any]:
            revision = workbench.state(session_id).session.get_revision(rev)
            return editor.residuals(session_id, revision.poses, revision.graph).as_dict()

        return call(session_id, summary)

    @router.get("/displacement")
    def displacement(
        session_id: str, before: Annotated[int, Query(ge=0)], after: Annotated[int | None, Query(ge=0)] = None
    ) -> dict[str, Any]:
        """Per-scan distance (m) each scan moved between two revisions (default: to the current one)."""
        from app.editing import displacements

        def compute() -> dict[str, Any]:
            session = workbench.state(session_id).session
            a, b = session.get_revision(before), session.get_revision(after)
            return {"before": a.number, "after": b.number, "displacement": displacements(a.poses, b.poses)}

        return call(session_id, compute)

    @router.get("/guess")
    def guess(
        session_id: str,
        data: Annotated[int, Query(ge=0)],
        model: Annotated[int | None, Query(ge=0)] = None,
        level: int = -1,
        top: Annotated[int, Query(ge=1, le=200)] = 10,
    ) -> dict[str, Any]:
        """Octree search for a pair: occupied cubes, ranked candidates with overlap scores, the winner."""
        return call(session_id, lambda: editor.guess_summary(session_id, data, model, level, top))

    @router.post("/guess/apply")
    def apply_guess(session_id: str, body: CandidateRequest, author: Author = "anonymous") -> dict[str, Any]:
        """ICP from the chosen candidate; the data scan moves to the result (a new revision)."""
        return call(
            session_id,
            lambda: editor.apply_candidate(session_id, body.data, body.model, body.candidate, author, body.level),
        )

    @router.get("/traces")
    def list_traces(session_id: str) -> list[dict[str, Any]]:
        """Stored traces of registration runs (newest last), replayable without recomputing."""
        return call(session_id, lambda: traces.list_traces(workbench.state(session_id).session))

    @router.get("/traces/{name}")
    def get_trace(session_id: str, name: str) -> dict[str, Any]:
        return call(session_id, lambda: traces.load_trace(workbench.state(session_id).session, name))

    return router
