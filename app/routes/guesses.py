"""REST for octree guesses: the ranked candidates of a pair's search, and ICP from a chosen one."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query
from pydantic import BaseModel, Field

from app.routes.dependencies import REQUIRE_SESSION, Author, EditorDep

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["guesses"], dependencies=[REQUIRE_SESSION])


class CandidateRequest(BaseModel):
    data: int = Field(ge=0)
    model: int | None = Field(None, ge=0)
    candidate: int = Field(0, ge=0, description="rank in the candidate list (0 = the search's winner)")
    level: int = -1


@router.get("/guess")
def guess(
    session_id: str,
    editor: EditorDep,
    data: Annotated[int, Query(ge=0)],
    model: Annotated[int | None, Query(ge=0)] = None,
    level: int = -1,
    top: Annotated[int, Query(ge=1, le=200)] = 10,
) -> dict[str, Any]:
    """Octree search for a pair: occupied cubes, ranked candidates with overlap scores, the winner."""
    return editor.guesses.summary(session_id, data, model, level, top)


@router.post("/guess/apply")
def apply_guess(
    session_id: str, body: CandidateRequest, editor: EditorDep, author: Author = "anonymous"
) -> dict[str, Any]:
    """ICP from the chosen candidate; the data scan moves to the result (a new revision)."""
    return editor.guesses.apply(session_id, body.data, body.model, body.candidate, author, body.level)
