"""REST for downloads: poses of any revision (KITTI, TUM, g2o, 3DTK .frames) and the merged map (PLY, LAZ)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import PlainTextResponse, Response

from app import exports
from app.errors import WorkbenchError
from app.routes.dependencies import SessionDep
from app.workbench import SessionState
from slam6d.errors import SessionError

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["exports"])
Revision = Annotated[int | None, Query(ge=0)]
Frame = Annotated[str, Query(pattern="^(canonical|native)$")]


@router.get("/poses", response_class=PlainTextResponse)
def poses(state: SessionDep, rev: Revision = None, frame: Frame = "canonical") -> Response:
    """KITTI lines (row-major 3x4 world_from_scan), canonical frame (metres, z up) unless frame=native."""
    return _poses_response(state, "kitti", rev, frame, attachment=False)


@router.get("/export/poses")
def export_poses(
    state: SessionDep,
    format: Annotated[str, Query(pattern="^(kitti|tum|frames|g2o)$")] = "kitti",
    rev: Revision = None,
    frame: Frame = "canonical",
) -> Response:
    """Trajectory as KITTI, TUM, g2o pose graph, or 3DTK .frames (zip, always the input's frame)."""
    return _poses_response(state, format, rev, frame, attachment=True)


@router.get("/export/map")
def export_map(
    state: SessionDep,
    format: Annotated[str, Query(pattern="^(ply|laz)$")] = "ply",
    voxel: Annotated[float, Query(ge=0.0, le=100.0, description="metres; 0 keeps every point")] = 0.0,
) -> Response:
    """The merged map at the current revision, in world coordinates (metres), optionally voxel-reduced."""
    with state.lock:
        content, media, filename = exports.export_map(state.sequence(), format, voxel)
    return Response(content, media_type=media, headers={"Content-Disposition": f'attachment; filename="{filename}"'})


def _poses_response(state: SessionState, fmt: str, rev: int | None, frame: str, attachment: bool) -> Response:
    session = state.session
    try:
        revision = session.get_revision(rev)
    except SessionError as exc:
        raise WorkbenchError(str(exc), 404 if rev is not None else 422) from None
    convention = session.config.convention if (frame == "native" or fmt == "frames") else None
    names = [p.stem for p in session.scan_files()]
    content, media, filename = exports.export_poses(revision.poses, fmt, convention, revision.graph, names)
    headers = {"X-Revision": str(revision.number)}
    if attachment:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    return Response(content, media_type=media, headers=headers)
