"""REST API: sessions, poses per revision, exports, undo/redo, background jobs.

Engine errors become 422 with the engine's message (which names the file and line); an unknown
session or job is 404. The author of an edit comes from the ``X-Author`` header (the web pages
send the name the user typed), so the journal says who did what.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Header, HTTPException, Query, Request, UploadFile
from fastapi.responses import PlainTextResponse, Response
from pydantic import BaseModel, Field

from app import exports
from app.data_root import SourceRefusedError
from app.jobs import JobConflictError
from app.workbench import UnknownSessionError, UploadError, Workbench
from slam6d.errors import Slam6dError
from slam6d.octree import reduce_points

Author = Annotated[str, Header(alias="X-Author", max_length=100)]


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


class JobRequest(BaseModel):
    kind: str = Field(description="'register' (the whole pipeline) or 'reload' (re-read and reduce the scans)")
    parameters: dict[str, Any] = Field(default_factory=dict)


def _state(workbench: Workbench, session_id: str):  # type: ignore[no-untyped-def]
    try:
        return workbench.state(session_id)
    except UnknownSessionError:
        raise HTTPException(404, f"no session '{session_id}'") from None
    except Slam6dError as exc:
        raise HTTPException(422, str(exc)) from None


def build_router(workbench: Workbench) -> APIRouter:
    router = APIRouter(prefix="/api")

    @router.get("/sessions", response_model=list[SessionSummary])
    def list_sessions() -> list[dict[str, Any]]:
        """Every session folder of the sessions directory."""
        return [workbench.summary(sid) for sid in workbench.session_ids()]

    @router.post("/sessions", status_code=201, response_model=SessionSummary)
    def create_session(body: CreateFromFolder) -> dict[str, Any]:
        """Create a session over a folder of scans under the server's data root (403 outside it)."""
        try:
            source = workbench.data_root.check(body.source)
        except SourceRefusedError as exc:
            raise HTTPException(exc.status, str(exc)) from None
        if not source.exists():
            raise HTTPException(422, f"{body.source}: no such file or directory")
        try:
            session = workbench.create_from_folder(body.name, source, body.format, body.frame)
        except Slam6dError as exc:
            raise HTTPException(422, str(exc)) from None
        return workbench.summary(session.id)

    @router.post("/sessions/upload", status_code=201, response_model=SessionSummary)
    async def upload_session(
        request: Request,
        name: Annotated[str, Form(min_length=1, max_length=200)],
        files: Annotated[list[UploadFile], File(description="scan files (with pose sidecars) or one .zip")],
        format: Annotated[str | None, Form()] = None,
        frame: Annotated[str | None, Form()] = None,
    ) -> dict[str, Any]:
        """Create a session from uploaded scans; all of them are parsed before anything is kept."""
        length = int(request.headers.get("content-length") or 0)
        if length > workbench.max_upload_bytes + 1024 * 1024:
            raise HTTPException(413, f"upload exceeds the limit of {workbench.max_upload_bytes // 2**20} MiB")
        contents = []
        total = 0
        for upload in files:
            data = await upload.read(workbench.max_upload_bytes + 1 - total)
            total += len(data)
            if total > workbench.max_upload_bytes:
                raise HTTPException(413, f"upload exceeds the limit of {workbench.max_upload_bytes // 2**20} MiB")
            contents.append((upload.filename or "", data))
        try:
            session = workbench.create_from_upload(name, contents, format or None, frame or None)
        except UploadError as exc:
            raise HTTPException(exc.status, str(exc)) from None
        except Slam6dError as exc:
            raise HTTPException(422, str(exc)) from None
        return workbench.summary(session.id)

    @router.get("/sessions/{session_id}")
    def session_details(session_id: str) -> dict[str, Any]:
        """Configuration, current revision, undo/redo state, scan files and recent journal entries."""
        state = _state(workbench, session_id)
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

    @router.get("/sessions/{session_id}/poses", response_class=PlainTextResponse)
    def poses(
        session_id: str,
        rev: Annotated[int | None, Query(ge=0)] = None,
        frame: Annotated[str, Query(pattern="^(canonical|native)$")] = "canonical",
    ) -> Response:
        """KITTI lines (row-major 3x4 world_from_scan), canonical frame (metres, z up) unless frame=native."""
        return _poses_response(workbench, session_id, "kitti", rev, frame, attachment=False)

    @router.get("/sessions/{session_id}/export/poses")
    def export_poses(
        session_id: str,
        format: Annotated[str, Query(pattern="^(kitti|tum|frames|g2o)$")] = "kitti",
        rev: Annotated[int | None, Query(ge=0)] = None,
        frame: Annotated[str, Query(pattern="^(canonical|native)$")] = "canonical",
    ) -> Response:
        """Trajectory as KITTI, TUM, g2o pose graph, or 3DTK .frames (zip, always the input's frame)."""
        return _poses_response(workbench, session_id, format, rev, frame, attachment=True)

    @router.get("/sessions/{session_id}/export/map")
    def export_map(
        session_id: str,
        format: Annotated[str, Query(pattern="^(ply|laz)$")] = "ply",
        voxel: Annotated[float, Query(ge=0.0, le=100.0, description="metres; 0 keeps every point")] = 0.0,
    ) -> Response:
        """The merged map at the current revision, in world coordinates (metres), optionally voxel-reduced."""
        state = _state(workbench, session_id)
        try:
            with state.lock:
                content, media, filename = exports.export_map(state.sequence(), format, voxel)
        except (Slam6dError, ValueError) as exc:
            raise HTTPException(422, str(exc)) from None
        return Response(
            content, media_type=media, headers={"Content-Disposition": f'attachment; filename="{filename}"'}
        )

    @router.get("/sessions/{session_id}/journal")
    def journal(session_id: str) -> list[dict[str, Any]]:
        return [e.__dict__ for e in _state(workbench, session_id).session.journal.entries()]

    @router.post("/sessions/{session_id}/undo")
    def undo(session_id: str, author: Author = "anonymous") -> dict[str, int]:
        _state(workbench, session_id)
        try:
            return {"revision": workbench.undo(session_id, author)}
        except Slam6dError as exc:
            raise HTTPException(409, str(exc)) from None

    @router.post("/sessions/{session_id}/redo")
    def redo(session_id: str, author: Author = "anonymous") -> dict[str, int]:
        _state(workbench, session_id)
        try:
            return {"revision": workbench.redo(session_id, author)}
        except Slam6dError as exc:
            raise HTTPException(409, str(exc)) from None

    @router.post("/sessions/{session_id}/jobs", status_code=202)
    def start_job(session_id: str, body: JobRequest, author: Author = "anonymous") -> dict[str, Any]:
        """Start background work on the session; poll ``GET /api/jobs/{id}``, cancel with ``DELETE``."""
        state = _state(workbench, session_id)
        if body.kind == "reload":
            voxel = float(body.parameters.get("voxel_size", state.session.config.engine.get("voxel_size", 0.1)))
            if not voxel > 0:
                raise HTTPException(422, "voxel_size must be positive")

            def work(progress, cancel):  # type: ignore[no-untyped-def]
                sequence = state.sequence(lambda d, t: progress("reading scans", d, t))
                kept = 0
                for index, scan in enumerate(sequence.scans):
                    if cancel():
                        from app.jobs import JobCancelledError

                        raise JobCancelledError()
                    kept += len(reduce_points(scan.points, voxel))
                    progress("reducing", index + 1, len(sequence))
                return {"scans": len(sequence), "points": sum(len(s) for s in sequence.scans), "reduced": kept}

        elif body.kind == "register":
            from app.registration import registration_job

            try:
                work = registration_job(workbench, session_id, author, body.parameters)
            except (Slam6dError, ValueError, TypeError) as exc:
                raise HTTPException(422, str(exc)) from None
        else:
            raise HTTPException(422, f"unknown job kind '{body.kind}'; known: register, reload")
        try:
            job = workbench.jobs.submit(session_id, body.kind, work, author, body.parameters)
        except JobConflictError as exc:
            raise HTTPException(409, str(exc)) from None
        return job.as_dict()

    @router.get("/jobs/{job_id}")
    def get_job(job_id: str) -> dict[str, Any]:
        job = workbench.jobs.get(job_id)
        if job is None:
            raise HTTPException(404, f"no job '{job_id}'")
        return job.as_dict()

    @router.delete("/jobs/{job_id}")
    def cancel_job(job_id: str) -> dict[str, Any]:
        job = workbench.jobs.cancel(job_id)
        if job is None:
            raise HTTPException(404, f"no job '{job_id}'")
        return job.as_dict()

    return router


def _poses_response(workbench: Workbench, session_id: str, fmt: str, rev: int | None, frame: str, attachment: bool):  # type: ignore[no-untyped-def]
    state = _state(workbench, session_id)
    session = state.session
    try:
        revision = session.get_revision(rev)
        convention = session.config.convention if (frame == "native" or fmt == "frames") else None
        names = [p.stem for p in session.scan_files()]
        content, media, filename = exports.export_poses(revision.poses, fmt, convention, revision.graph, names)
    except Slam6dError as exc:
        status = 404 if rev is not None and "no revision" in str(exc) else 422
        raise HTTPException(status, str(exc)) from None
    headers = {"X-Revision": str(revision.number)}
    if attachment:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    return Response(content, media_type=media, headers=headers)
