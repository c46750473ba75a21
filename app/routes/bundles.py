"""REST for session bundles: download a session's whole history as a zip, or import one as a new session.

The engine does the work (:mod:`slam6d.bundle`); here the bundle is written to a temporary file
streamed back and deleted afterwards, and an upload is streamed to disk, bounded by the upload
limit, imported on a worker thread and its scans parsed in a child process under the parse time
limit (as an upload's). A bundle without its scans records where its scans were
(inside the exporting server's data root) and every scan file's sha256: this server re-links the
session to the same files under its own ``--data-root`` after checking every hash, and refuses the
bundle, naming what is missing, when they are not there (it never opens a folder outside its data
root).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, File, Query, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from starlette.background import BackgroundTask

from app.routes.dependencies import Author, SessionDep, WorkbenchDep
from app.routes.sessions import SessionSummary
from slam6d.archive import ArchiveLimits
from slam6d.bundle import export_bundle, import_bundle
from slam6d.session import Session

router = APIRouter(prefix="/api/sessions", tags=["bundles"])


@router.get("/{session_id}/bundle", response_class=FileResponse)
def download_bundle(
    session_id: str,
    state: SessionDep,
    workbench: WorkbenchDep,
    scans: Annotated[bool, Query(description="include the scan files themselves")] = False,
) -> FileResponse:
    """The session as a zip: manifest (sha256 per file), session.toml, journal, traces, camera path, and the
    scans (``scans=true``) or the record of where they are and their hashes (re-linked on import)."""
    scratch = Path(tempfile.mkdtemp(prefix="bundle-"))
    try:
        summary = export_bundle(
            state.session, scratch / f"{session_id}.zip", include_scans=scans, data_root=workbench.data_root.folder
        )
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    return FileResponse(
        summary.path,
        media_type="application/zip",
        filename=f"{session_id}.zip",
        background=BackgroundTask(shutil.rmtree, scratch, ignore_errors=True),
    )


@router.post("/import", status_code=201, response_model=SessionSummary)
async def import_session(
    workbench: WorkbenchDep,
    file: Annotated[UploadFile, File(description="a bundle from GET /api/sessions/{id}/bundle")],
    author: Author = "anonymous",
) -> dict[str, Any]:
    """A new session with the bundle's history; a bundle failing any check (names, links, nested
    archives, size, ratio, hashes, journal, scans neither in it nor found under the data root with
    their recorded hashes) is refused with the reason and writes nothing."""
    limits = ArchiveLimits(max_total_bytes=workbench.max_upload_bytes)
    label = file.filename or "bundle"

    def import_and_parse() -> Session:
        session = import_bundle(file.file, workbench.sessions_dir, limits, workbench.data_root.locate, author, label)
        return workbench.check_imported(session, f"bundle '{label}'")  # its scans parse, in time

    session = await run_in_threadpool(import_and_parse)
    return workbench.summary(session.id)
