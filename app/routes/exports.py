"""REST for downloads: poses of any revision (KITTI, TUM, g2o, 3DTK .frames) and the merged map (PLY, LAZ)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import FileResponse, PlainTextResponse, Response
from starlette.background import BackgroundTask

from app import exports
from app.errors import WorkbenchError
from app.routes.dependencies import EditorDep, SessionDep
from app.validation import RevisionQuery
from app.workbench import SessionState
from slam6d.errors import SessionError
from slam6d.geometry import Matrix
from slam6d.journal import Revision

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["exports"])
RevisionNumber = RevisionQuery
Frame = Annotated[str, Query(pattern="^(canonical|native)$")]


@router.get("/poses", response_class=PlainTextResponse)
def poses(state: SessionDep, rev: RevisionNumber = None, frame: Frame = "canonical") -> Response:
    """KITTI lines (row-major 3x4 world_from_scan), canonical frame (metres, z up) unless frame=native."""
    return _poses_response(state, "kitti", rev, frame, attachment=False)


@router.get("/export/poses")
def export_poses(
    session_id: str,
    state: SessionDep,
    editor: EditorDep,
    format: Annotated[str, Query(pattern="^(kitti|tum|frames|g2o)$")] = "kitti",
    rev: RevisionNumber = None,
    frame: Frame = "canonical",
) -> Response:
    """Trajectory as KITTI, TUM, g2o pose graph (with each edge's information from the scans' overlap),
    or 3DTK .frames (zip, always the input's frame)."""
    information = None
    if format == "g2o":
        revision = _revision(state, rev)
        information = editor.context.edge_information(session_id, revision.poses, revision.graph)
    return _poses_response(state, format, rev, frame, attachment=True, information=information)


@router.get("/export/map")
def export_map(
    state: SessionDep,
    format: Annotated[str, Query(pattern="^(ply|laz)$")] = "ply",
    voxel: Annotated[float, Query(ge=0.0, le=100.0, description="metres; 0 keeps every point")] = 0.0,
) -> Response:
    """The merged map at the current revision, in world coordinates (metres), optionally voxel-reduced."""
    scratch = Path(tempfile.mkdtemp(prefix="map-"))
    try:
        with state.lock:
            path, media, filename = exports.export_map(state.sequence(), format, scratch, voxel)
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    cleanup = BackgroundTask(shutil.rmtree, scratch, ignore_errors=True)
    return FileResponse(path, media_type=media, filename=filename, background=cleanup)


def _revision(state: SessionState, rev: int | None) -> Revision:
    try:
        return state.session.get_revision(rev)
    except SessionError as exc:
        raise WorkbenchError(str(exc), 404 if rev is not None else 422) from None


def _poses_response(
    state: SessionState,
    fmt: str,
    rev: int | None,
    frame: str,
    attachment: bool,
    information: list[Matrix] | None = None,
) -> Response:
    session = state.session
    revision = _revision(state, rev)
    convention = session.config.convention if (frame == "native" or fmt == "frames") else None
    names = [p.stem for p in session.scan_files()]
    content, media, filename = exports.export_poses(revision.poses, fmt, convention, revision.graph, names, information)
    headers = {"X-Revision": str(revision.number)}
    if attachment:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    return Response(content, media_type=media, headers=headers)
