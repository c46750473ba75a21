"""REST for sharing: who am I on this server, and a session's share links (owners only).

A share link is a session token in a page address (``/sessions/{id}?token=...``); opening it sets
the token as this server's cookie. Owners create links with a role up to their own and revoke
them; the secret is in the answer to the creating request only - the server keeps its hash.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Request
from pydantic import BaseModel, Field

from app.guard import OPEN_GRANT, is_open, requires
from app.tokens import Grant, Role, TokenError, TokenStore, parse_duration


class ShareRequest(BaseModel):
    role: Literal["viewer", "reviewer", "editor", "owner"] = "viewer"
    name: Annotated[str, Field(min_length=1, max_length=100, description="who the link is for")]
    expires: Annotated[str, Field(max_length=20, description="30m, 12h, 7d, 2w or never")] = "7d"


def grant_of(request: Request) -> Grant:
    return getattr(request.state, "grant", OPEN_GRANT)


def build_sharing_router(tokens: TokenStore) -> APIRouter:
    router = APIRouter(prefix="/api", tags=["sharing"])

    @router.get("/me", openapi_extra=requires(Role.viewer, any_session=True))
    def me(request: Request) -> dict[str, Any]:
        """The role and name this browser acts with (``open``: a loopback server without tokens, where the
        name is the one typed in the page header)."""
        grant = grant_of(request)
        return {"role": grant.role.name, "name": grant.name, "session": grant.session, "open": is_open(grant)}

    @router.get("/sessions/{session_id}/tokens", openapi_extra=requires(Role.owner))
    def list_links(session_id: str) -> list[dict[str, Any]]:
        """The tokens valid on this session (its share links and the server-wide ones), never their secrets."""
        return [g.as_dict() for g in tokens.grants(session_id)]

    @router.post("/sessions/{session_id}/tokens", status_code=201, openapi_extra=requires(Role.owner))
    def create_link(session_id: str, body: ShareRequest, request: Request) -> dict[str, Any]:
        """A share link for this session with a role up to the creator's own."""
        role = Role.parse(body.role)
        if role > grant_of(request).role:
            raise HTTPException(403, f"a {grant_of(request).role.name} cannot hand out {role.name} links")
        try:
            secret, grant = tokens.issue(role, session_id, parse_duration(body.expires), body.name)
        except TokenError as exc:
            raise HTTPException(422, str(exc)) from None
        link = f"{str(request.base_url).rstrip('/')}/sessions/{session_id}?token={secret}"
        return {"token": secret, "link": link, "grant": grant.as_dict()}

    @router.delete("/sessions/{session_id}/tokens/{token_id}", openapi_extra=requires(Role.owner))
    def revoke_link(session_id: str, token_id: str, request: Request) -> dict[str, Any]:
        """Revoke one of this session's links (a server-wide token only by a server-wide owner)."""
        found = next((g for g in tokens.grants(session_id) if g.id == token_id), None)
        if found is None:
            raise HTTPException(404, f"no token '{token_id}' on session '{session_id}'")
        if found.session is None and grant_of(request).session is not None:
            raise HTTPException(403, "a session's owner cannot revoke a server-wide token")
        return tokens.revoke(token_id).as_dict()

    return router


__all__ = ["build_sharing_router"]
