"""What routes take from the request: the workbench, a session's state (404 when unknown), the editor, the author.

A route that names ``state: SessionDep`` never runs for an unknown session id; the lookup and
its error live here once (the status itself is chosen in :mod:`app.routes.errors`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Header, Request
from starlette.requests import HTTPConnection

from app.editing import Editor, editor_for
from app.guard import OPEN_GRANT
from app.jobs import Work
from app.tokens import Grant
from app.workbench import SessionState, Workbench


def get_workbench(request: Request) -> Workbench:
    workbench: Workbench = request.app.state.workbench
    return workbench


WorkbenchDep = Annotated[Workbench, Depends(get_workbench)]


def session_state(session_id: str, workbench: WorkbenchDep) -> SessionState:
    """The session named in the path, opened once; UnknownSessionError (404) when there is none."""
    return workbench.state(session_id)


def get_editor(workbench: WorkbenchDep) -> Editor:
    return editor_for(workbench)


SessionDep = Annotated[SessionState, Depends(session_state)]
# for routers and routes that need the session to exist but not its state
REQUIRE_SESSION = Depends(session_state)
EditorDep = Annotated[Editor, Depends(get_editor)]


def author_name(
    connection: HTTPConnection,
    x_author: Annotated[
        str | None,
        Header(
            alias="X-Author",
            description="who acts, on a server without tokens (a token's holder is the token's name): "
            "plain text, or percent-encoded UTF-8 as UTF-8''%E5%BC%A0%E4%BC%9F",
        ),
    ] = None,
) -> str:
    """Who acts: the name the request guard settled on (:mod:`app.guard`, which read and checked
    ``X-Author``), so journal, comments, presence and ``/api/me`` show one and the same name."""
    grant: Grant = connection.scope.get("state", {}).get("grant", OPEN_GRANT)
    return grant.name or "anonymous"


# who made an edit: the web pages send the name the user typed, so the journal says who did what
Author = Annotated[str, Depends(author_name)]


@dataclass(frozen=True)
class Actor:
    """Who acts on the session named in the path (the name their page sends), and the workbench they act
    through: what every route that changes a session needs, taken from the request once."""

    workbench: Workbench
    session_id: str
    author: str

    def start_job(self, kind: str, work: Work, parameters: dict[str, Any] | None = None) -> dict[str, Any]:
        """Background work on the session (routes answering 202); polled at ``GET /api/jobs/{id}``."""
        return self.workbench.jobs.submit(self.session_id, kind, work, self.author, parameters or {}).as_dict()

    def notify(self) -> None:
        """Tell the session's 3D views that something they draw changed."""
        self.workbench.notify(self.session_id)


def actor(session_id: str, workbench: WorkbenchDep, author: Author = "anonymous") -> Actor:
    return Actor(workbench, session_id, author)


ActorDep = Annotated[Actor, Depends(actor)]
