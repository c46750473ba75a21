"""REST for the stored traces of registration runs, replayable without recomputing."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from app import traces
from app.routes.dependencies import SessionDep

router = APIRouter(prefix="/api/sessions/{session_id}", tags=["traces"])


@router.get("/traces")
def list_traces(state: SessionDep) -> list[dict[str, Any]]:
    """Stored traces of registration runs (newest last)."""
    return traces.list_traces(state.session)


@router.get("/traces/{name}")
def get_trace(state: SessionDep, name: str) -> dict[str, Any]:
    """One stored trace: the run's initial poses and every event, as JSON."""
    return traces.load_trace(state.session, name)
