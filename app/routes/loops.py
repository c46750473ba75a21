"""REST for loops: the hypotheses to review, detecting them, accepting or rejecting one, closing the accepted ones.

Finding loops changes nothing (its result is the review list); accepting or rejecting one is a new
revision of the graph; loop closing (error diffusion) is a job answering 202, polled at
``GET /api/jobs/{id}``.
"""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter

from app.guard import requires
from app.routes.dependencies import REQUIRE_SESSION, ActorDep, Author, EditorDep
from app.tokens import Role
from app.validation import IndexPath

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["loops"], dependencies=[REQUIRE_SESSION])


@router.get("/loops")
def loops(session_id: str, editor: EditorDep) -> list[dict[str, Any]]:
    """The latest loop hypotheses (scan pair, distance, overlap, ICP fitness) with their review status."""
    return editor.loops.listed(session_id)


@router.post("/loops/detect", status_code=202)
def detect_loops(session_id: str, editor: EditorDep, actor: ActorDep) -> dict[str, Any]:
    """Find and verify loop hypotheses from the current poses (a job); the result is the review list."""
    return actor.start_job("detect-loops", editor.loops.detect_job(session_id, actor.author))


@router.post("/loops/{k}/{decision}", openapi_extra=requires(Role.reviewer))
def decide_loop(
    session_id: str,
    k: IndexPath,
    decision: Literal["accept", "reject"],
    editor: EditorDep,
    author: Author = "anonymous",
) -> dict[str, Any]:
    """Accept hypothesis ``k`` (its ICP-verified edge joins the graph) or reject it (the refusal is
    recorded); either way a new revision."""
    return editor.loops.decide(session_id, k, decision == "accept", author)


@router.post("/close-loops", status_code=202)
def close_loops(session_id: str, editor: EditorDep, actor: ActorDep) -> dict[str, Any]:
    """Error diffusion over the accepted loop and manual edges (a job)."""
    return actor.start_job("close-loops", editor.relaxation.close_loops_job(session_id, actor.author))
