"""Comments on a session: notes anchored to a scan point, an edge or a loop hypothesis.

A comment on a scan holds its point in *that scan's own frame*, so when the scan is re-registered
(moved, relaxed, undone) the note moves with it: its place in the world is computed per revision
(``world_from_scan @ point``). A comment on an edge or a loop hypothesis sits between the two
scans' origins. Each comment has an id, its text, author, time and status (open or resolved).

The comments are one document in the session's journal (kind ``comments``), changed in place
inside the journal's write transaction, so two people commenting at once both keep theirs and
every change has its author and time in the history.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field, model_validator

from app.errors import EditError
from slam6d.geometry import Matrix
from slam6d.journal import now
from slam6d.session import Session

KIND = "comments"
Status = Literal["open", "resolved"]


class Anchor(BaseModel):
    """Exactly one of: ``scan`` (with ``point`` in its own frame, metres), ``edge`` or ``loop`` (a scan pair)."""

    scan: int | None = Field(None, ge=0)
    point: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0], min_length=3, max_length=3)
    edge: list[int] | None = Field(None, min_length=2, max_length=2)
    loop: list[int] | None = Field(None, min_length=2, max_length=2)

    @model_validator(mode="after")
    def one_anchor(self) -> Anchor:
        given = [name for name in ("scan", "edge", "loop") if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError(f"a comment is anchored to exactly one of scan, edge or loop (got {given or 'none'})")
        if not all(np.isfinite(self.point)) or max(abs(v) for v in self.point) > 1e6:
            raise ValueError("point must be three finite coordinates within 1e6 m")
        return self

    def scans(self) -> list[int]:
        return [self.scan] if self.scan is not None else list(self.edge or self.loop or [])

    def stored(self) -> dict[str, Any]:
        if self.scan is not None:
            return {"scan": self.scan, "point": [float(v) for v in self.point]}
        return {"edge": self.edge} if self.edge is not None else {"loop": self.loop}


def comments_of(session: Session) -> list[dict[str, Any]]:
    latest = session.journal.latest(KIND)
    return [] if latest is None else list(latest.parameters.get("comments", []))


def add_comment(session: Session, anchor: Anchor, text: str, author: str) -> dict[str, Any]:
    """Store a new open comment; EditError (404) for a scan the session does not have."""
    count = len(session.poses())
    for k in anchor.scans():
        if not 0 <= k < count:
            raise EditError(f"no scan {k}; the session has scans 0..{count - 1}", 404)
    added: dict[str, Any] = {}

    def change(doc: dict[str, Any] | None) -> dict[str, Any]:
        comments = list((doc or {}).get("comments", []))
        number = 1 + max((int(c["id"]) for c in comments), default=0)
        added.update(
            id=number, anchor=anchor.stored(), text=text, author=author or "anonymous", time=now(), status="open"
        )
        return {"comments": [*comments, dict(added)]}

    session.journal.update_document(author, KIND, change)
    return added


def set_status(session: Session, comment_id: int, status: Status, author: str) -> dict[str, Any]:
    """Resolve or reopen a comment (who and when is recorded); EditError (404) for an unknown id."""
    changed: dict[str, Any] = {}

    def change(doc: dict[str, Any] | None) -> dict[str, Any]:
        comments = [dict(c) for c in (doc or {}).get("comments", [])]
        found = next((c for c in comments if int(c["id"]) == comment_id), None)
        if found is None:
            raise EditError(f"no comment {comment_id}", 404)
        found.update(status=status, status_by=author or "anonymous", status_time=now())
        changed.update(found)
        return {"comments": comments}

    session.journal.update_document(author, KIND, change)
    return changed


def world_position(anchor: dict[str, Any], poses: list[Matrix]) -> list[float] | None:
    """Where an anchor is at a revision's poses (canonical world, metres); None if its scans are gone."""
    if "scan" in anchor:
        k = int(anchor["scan"])
        if not 0 <= k < len(poses):
            return None
        return [float(v) for v in (np.asarray(poses[k]) @ np.array([*anchor["point"], 1.0]))[:3]]
    i, j = (int(v) for v in anchor.get("edge") or anchor.get("loop") or [-1, -1])
    if not (0 <= i < len(poses) and 0 <= j < len(poses)):
        return None
    return [float(v) for v in 0.5 * (np.asarray(poses[i])[:3, 3] + np.asarray(poses[j])[:3, 3])]


def placed_comments(session: Session, rev: int | None = None) -> list[dict[str, Any]]:
    """Every comment with its ``world`` position at revision ``rev`` (default: the current one)."""
    poses = session.poses(rev)
    return [{**c, "world": world_position(c["anchor"], poses)} for c in comments_of(session)]


__all__ = ["Anchor", "add_comment", "comments_of", "placed_comments", "set_status", "world_position"]
