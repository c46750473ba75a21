"""REST for sessions: list, create (from a server folder or an upload), details, journal, undo/redo."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Request, UploadFile
from pydantic import BaseModel, Field

from app.errors import UploadError
from app.routes.dependencies import REQUIRE_SESSION, Author, SessionDep, WorkbenchDep

router = APIRouter(prefix="/api/sessions", tags=["sessions"])


class SessionSummary(BaseModel):
    id: str
    name: str
    scans: int
    revision: int
    format: str
    error: str | None = None


class CreateFromFolder(BaseModel):
    name: str = Field(min_length=1, max_length=200)
    source: str = Field(min_length=1, description="a folder of scans (or one scan file) on the server")
    format: str | None = None
    frame: str | None = None


@router.get("", response_model=list[SessionSummary])
def list_sessions(workbench: WorkbenchDep) -> list[dict[str, Any]]:
    """Every session folder of the sessions directory."""
    return [workbench.summary(sid) for sid in workbench.session_ids()]


@router.post("", status_code=201, response_model=SessionSummary)
def create_session(body: CreateFromFolder, workbench: WorkbenchDep) -> dict[str, Any]:
    """Create a session over a folder of scans that already lives on the server."""
    if not Path(body.source).expanduser().exists():
        raise UploadError(f"{body.source}: no such file or directory")
    session = workbench.create_from_folder(body.name, Path(body.source), body.format, body.frame)
    return workbench.summary(session.id)


@router.post("/upload", status_code=201, response_model=SessionSummary)
async def upload_session(
    request: Request,
    workbench: WorkbenchDep,
    name: Annotated[str, Form(min_length=1, max_length=200)],
    files: Annotated[list[UploadFile], File(description="scan files (with pose sidecars) or one .zip")],
    format: Annotated[str | None, Form()] = None,
    frame: Annotated[str | None, Form()] = None,
) -> dict[str, Any]:
    """Create a session from uploaded scans; all of them are parsed before anything is kept."""
    limit = workbench.max_upload_bytes
    too_large = UploadError(f"upload exceeds the limit of {limit // 2**20} MiB", 413)
    if int(request.headers.get("content-length") or 0) > limit + 1024 * 1024:
        raise too_large
    contents = []
    total = 0
    for upload in files:
        data = await upload.read(limit + 1 - total)
        total += len(data)
        if total > limit:
            raise too_large
        contents.append((upload.filename or "", data))
    session = workbench.create_from_upload(name, contents, format or None, frame or None)
    return workbench.summary(session.id)


@router.get("/{session_id}")
def session_details(session_id: str, state: SessionDep, workbench: WorkbenchDep) -> dict[str, Any]:
    """Configuration, current revision, undo/redo state, scan files and recent journal entries."""
    session = state.session
    config = session.config
    journal = session.journal.entries()
    return {
        **workbench.summary(session_id),
        "config": {
            "sources": list(config.sources),
            "format": config.format_name,
            "frame": config.frame,
            "metres_per_unit": config.convention.metres_per_unit,
            "min_range": config.min_range,
            "max_range": config.max_range,
            "engine": config.engine,
            "created": config.created,
        },
        "scan_files": [p.name for p in session.scan_files()],
        "revisions": session.journal.revisions(),
        "can_undo": session.journal.can_undo(),
        "can_redo": session.journal.can_redo(),
        "journal": [e.__dict__ for e in journal[-50:]],
        "jobs": [j.as_dict() for j in workbench.jobs.for_session(session_id)],
    }


@router.get("/{session_id}/journal")
def journal(state: SessionDep) -> list[dict[str, Any]]:
    """Every journal entry, oldest first: revisions with author, kind and parameters, and review lists."""
    return [e.__dict__ for e in state.session.journal.entries()]


@router.post("/{session_id}/undo", dependencies=[REQUIRE_SESSION])
def undo(session_id: str, workbench: WorkbenchDep, author: Author = "anonymous") -> dict[str, int]:
    """Back to the parent revision (409 when there is nothing to undo)."""
    return {"revision": workbench.undo(session_id, author)}


@router.post("/{session_id}/redo", dependencies=[REQUIRE_SESSION])
def redo(session_id: str, workbench: WorkbenchDep, author: Author = "anonymous") -> dict[str, int]:
    """Forward to the revision last undone (409 when there is nothing to redo)."""
    return {"revision": workbench.redo(session_id, author)}
