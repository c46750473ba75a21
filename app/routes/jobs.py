"""REST for background jobs: start a registration or reload, poll a job, cancel it.

Jobs started elsewhere (loop detection, loop closing, relaxation, renders) are polled and cancelled
here too.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import Field

from app.errors import EditError, WorkbenchError
from app.jobs import Cancel, Progress, Work
from app.registration import registration_job
from app.routes.dependencies import ActorDep, SessionDep, WorkbenchDep
from app.validation import RequestBody
from app.workbench import SessionState
from slam6d.errors import Cancelled
from slam6d.octree import reduce_points

router = APIRouter(prefix="/api", tags=["jobs"])


class JobRequest(RequestBody):
    kind: str = Field(description="'register' (the whole pipeline) or 'reload' (re-read and reduce the scans)")
    parameters: dict[str, Any] = Field(default_factory=dict, max_length=100)


def reload_job(state: SessionState, parameters: dict[str, Any]) -> Work:
    """Re-read the scans and reduce each to ``voxel_size`` (default: the session's engine setting)."""
    try:
        voxel = float(parameters.get("voxel_size", state.session.config.engine.get("voxel_size", 0.1)))
    except (TypeError, ValueError):
        raise WorkbenchError(f"voxel_size must be a number, got {parameters.get('voxel_size')!r}") from None
    if not voxel > 0:
        raise WorkbenchError("voxel_size must be positive")

    def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
        sequence = state.sequence(lambda d, t: progress("reading scans", d, t))
        kept = 0
        for index, scan in enumerate(sequence.scans):
            if cancel():
                raise Cancelled("reload cancelled")
            kept += len(reduce_points(scan.points, voxel))
            progress("reducing", index + 1, len(sequence))
        return {"scans": len(sequence), "points": sum(len(s) for s in sequence.scans), "reduced": kept}

    return work


@router.post("/sessions/{session_id}/jobs", status_code=202)
def start_job(body: JobRequest, state: SessionDep, actor: ActorDep) -> dict[str, Any]:
    """Start background work on the session; poll ``GET /api/jobs/{id}``, cancel with ``DELETE``."""
    if body.kind == "reload":
        work = reload_job(state, body.parameters)
    elif body.kind == "register":
        work = registration_job(actor.workbench, actor.session_id, actor.author, body.parameters)
    else:
        raise WorkbenchError(f"unknown job kind '{body.kind}'; known: register, reload")
    return actor.start_job(body.kind, work, body.parameters)


@router.get("/jobs/{job_id}")
def get_job(job_id: str, workbench: WorkbenchDep) -> dict[str, Any]:
    """A job's status, stage, progress and (once done) result."""
    job = workbench.jobs.get(job_id)
    if job is not None:
        return job.as_dict()
    recorded = workbench.recorded_job(job_id)  # a job of an earlier server process, e.g. cut short by a crash
    if recorded is None:
        raise EditError(f"no job '{job_id}'", 404)
    return recorded


@router.delete("/jobs/{job_id}")
def cancel_job(job_id: str, workbench: WorkbenchDep) -> dict[str, Any]:
    """Ask a job to stop; it ends as ``cancelled`` at its next check."""
    job = workbench.jobs.cancel(job_id)
    if job is None:
        raise EditError(f"no job '{job_id}'", 404)
    return job.as_dict()
