"""REST for loops: the hypotheses to review, detecting them, accepting or rejecting one, closing the accepted ones.

Finding loops changes nothing (its result is the review list); accepting or rejecting one is a new
revision of the graph; loop closing (error diffusion) is a job answering 202, polled at
``GET /api/jobs/{id}``.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from app.routes.dependencies import REQUIRE_SESSION, Author, EditorDep, WorkbenchDep

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["loops"], dependencies=[REQUIRE_SESSION])


@router.get("/loops")
def loops(session_id: str, editor: EditorDep) -> list[dict[str, Any]]:
    """The latest loop hypotheses (scan pair, distance, overlap, ICP fitness) with their review status."""
    return editor.loops.listed(session_id)


@router.post("/loops/detect", status_code=202)
def detect_loops(
    session_id: str, editor: EditorDep, workbench: WorkbenchDep, author: Author = "anonymous"
) -> dict[str, Any]:
    """Find and verify loop hypotheses from the current poses (a job); the result is the review list."""
    work = editor.loops.detect_job(session_id, author)
    return workbench.jobs.submit(session_id, "detect-loops", work, author, {}).as_dict()


@router.post("/loops/{k}/accept")
def accept_loop(session_id: str, k: int, editor: EditorDep, author: Author = "anonymous") -> dict[str, Any]:
    """Hypothesis ``k``'s ICP-verified edge joins the graph (a new revision)."""
    return editor.loops.decide(session_id, k, True, author)


@router.post("/loops/{k}/reject")
def reject_loop(session_id: str, k: int, editor: EditorDep, author: Author = "anonymous") -> dict[str, Any]:
    """Hypothesis ``k`` is turned down (a new revision recording it)."""
    return editor.loops.decide(session_id, k, False, author)


@router.post("/close-loops", status_code=202)
def close_loops(
    session_id: str, editor: EditorDep, workbench: WorkbenchDep, author: Author = "anonymous"
) -> dict[str, Any]:
    """Error diffusion over the accepted loop and manual edges (a job)."""
    work = editor.relaxation.close_loops_job(session_id, author)
    return workbench.jobs.submit(session_id, "close-loops", work, author, {}).as_dict()
