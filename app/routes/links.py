"""REST for permalinks: a session page's link parameters checked against the session and described.

The session page asks this when it opens a link (``/sessions/{id}?rev=&cam=&sel=&colour=``, see
:mod:`app.permalink`) and restores what the answer says; the page route itself refuses the same
bad parameters (422 naming the parameter) before any page is served.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query

from app.permalink import parse_link, resolve_link
from app.routes.dependencies import EditorDep, SessionDep

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["view"])
LinkText = Annotated[str | None, Query(max_length=400)]


@router.get("/link")
def link(
    state: SessionDep,
    editor: EditorDep,
    rev: LinkText = None,
    cam: LinkText = None,
    sel: LinkText = None,
    colour: LinkText = None,
) -> dict[str, Any]:
    """What a permalink restores: ``revision`` (``old`` when not the head, which is then read-only),
    ``camera`` (position, look_at, up, fov_deg; canonical frame), ``selection`` (the scan, edge or loop
    hypothesis as it is at that revision) and ``colour``; 422 naming the parameter that cannot be used."""
    query = {k: v for k, v in {"rev": rev, "cam": cam, "sel": sel, "colour": colour}.items() if v is not None}
    return resolve_link(state, editor, parse_link(query))
