"""REST for the pose graph by hand: list, add (ICP-refined) and delete edges, and move a scan.

Every change answers with the new ``revision``; a move also answers the residuals before and after
and a warning when they jumped.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import Field

from app.routes.dependencies import REQUIRE_SESSION, Author, EditorDep
from app.validation import Index, IndexPath, RequestBody, RigidPose

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["edges"], dependencies=[REQUIRE_SESSION])


class EdgeRequest(RequestBody):
    i: Index
    j: Index
    force: bool = Field(False, description="store the edge even when ICP does not confirm the match")


class PoseRequest(RequestBody):
    pose: RigidPose = Field(description="4x4 world_from_scan, canonical frame (metres, z up)")
    refine: bool = Field(False, description="run ICP from this pose against the scan's graph neighbours")
    carry: list[Index] = Field(
        default_factory=list,
        max_length=100_000,
        description="scans moved rigidly with this one (e.g. its connected component, to bridge it to the rest); "
        "ICP then matches only against graph neighbours outside them",
    )


@router.get("/edges")
def edges(session_id: str, editor: EditorDep) -> list[dict[str, Any]]:
    """The current pose graph's edges; ``k`` is what ``DELETE .../edges/{k}`` takes."""
    return editor.edges.listed(session_id)


@router.post("/edges", status_code=201)
def add_edge(session_id: str, body: EdgeRequest, editor: EditorDep, author: Author = "anonymous") -> dict[str, Any]:
    """A loop edge between scans i and j, refined by ICP (422 when they do not match, unless ``force``)."""
    return editor.edges.add(session_id, body.i, body.j, author, body.force)


@router.delete("/edges/{k}")
def delete_edge(session_id: str, k: IndexPath, editor: EditorDep, author: Author = "anonymous") -> dict[str, Any]:
    """Edge ``k`` leaves the graph (a new revision)."""
    return editor.edges.delete(session_id, k, author)


@router.post("/scans/{k}/pose")
def move_scan(
    session_id: str, k: IndexPath, body: PoseRequest, editor: EditorDep, author: Author = "anonymous"
) -> dict[str, Any]:
    """Place a scan by hand (optionally ICP from there, optionally carrying other scans along); answers the
    residuals before/after and any warning."""
    return editor.edges.move_scan(session_id, k, body.pose, author, body.refine, body.carry)  # type: ignore[arg-type]
