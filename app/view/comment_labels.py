"""Comments in the 3D view: each one a label at its place in the revision shown.

Labels are redrawn whenever the session changes (a new revision moves a scan's notes with it; a
comment added or resolved elsewhere appears for everyone). Resolved comments stay, marked, so a
reviewer sees what was discussed.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

from app.comments import placed_comments

_drawn: weakref.WeakKeyDictionary[Any, list[Any]] = weakref.WeakKeyDictionary()
_lock = threading.Lock()
READY_TIMEOUT = 300.0  # seconds a new view may take to read its scans before its labels are drawn


def label_text(comment: dict[str, Any]) -> str:
    text = comment["text"] if len(comment["text"]) <= 60 else comment["text"][:59] + "…"
    done = " (resolved)" if comment.get("status") == "resolved" else ""
    return f"#{comment['id']} {comment['author']}: {text}{done}"


def show_comments(viewer: Any) -> None:
    """Replace the view's comment labels by the session's comments at the revision it shows."""
    if viewer is None or not viewer.ready.is_set() or viewer.error:
        return
    comments = placed_comments(viewer.state.session)
    with _lock:
        for node in _drawn.pop(viewer, []):
            node.remove()
        _drawn[viewer] = [
            viewer.server.scene.add_label(f"/comments/{c['id']}", label_text(c), position=tuple(c["world"]))
            for c in comments
            if c["world"] is not None
        ]


def show_when_ready(viewer: Any) -> None:
    """Draw the labels once a newly started view has its scans (in the background)."""

    def wait() -> None:
        if viewer.ready.wait(READY_TIMEOUT):
            show_comments(viewer)

    threading.Thread(target=wait, name="comment-labels", daemon=True).start()


__all__ = ["label_text", "show_comments", "show_when_ready"]
