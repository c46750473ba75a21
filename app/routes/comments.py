"""REST for comments: list them placed at a revision, add one (anchored to a scan point, an edge or a
loop hypothesis), resolve or reopen one. Commenting needs the reviewer role."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query
from pydantic import BaseModel, Field

from app.comments import Anchor, Status, add_comment, placed_comments, set_status
from app.guard import requires
from app.routes.dependencies import ActorDep, SessionDep
from app.tokens import Role

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["comments"])


class CommentRequest(BaseModel):
    anchor: Anchor
    text: str = Field(min_length=1, max_length=2000)


class StatusRequest(BaseModel):
    status: Status


@router.get("/comments")
def list_comments(state: SessionDep, rev: Annotated[int | None, Query(ge=0)] = None) -> list[dict[str, Any]]:
    """Every comment with its ``world`` position (canonical frame, metres) at revision ``rev`` (default: current)."""
    return placed_comments(state.session, rev)


@router.post("/comments", status_code=201, openapi_extra=requires(Role.reviewer))
def create_comment(body: CommentRequest, state: SessionDep, actor: ActorDep) -> dict[str, Any]:
    """A new open comment; a scan's ``point`` is in that scan's own frame, so the note moves with the scan."""
    added = add_comment(state.session, body.anchor, body.text, actor.author)
    actor.notify()  # the 3D views redraw their labels
    return added


@router.post("/comments/{comment_id}/status", openapi_extra=requires(Role.reviewer))
def change_status(comment_id: int, body: StatusRequest, state: SessionDep, actor: ActorDep) -> dict[str, Any]:
    """Resolve (or reopen) a comment."""
    changed = set_status(state.session, comment_id, body.status, actor.author)
    actor.notify()
    return changed
