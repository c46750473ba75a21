"""How a background job shows in a panel: its start button, cancel button, progress bar and status line.

The registration folder and the fly-through folder both follow their jobs this way, so a user
reads every long task the same.
"""

from __future__ import annotations

from typing import Any


def show_job_progress(job: Any, start: Any, cancel: Any, progress: Any, status: Any, label: str) -> None:
    """While ``job`` runs: start disabled, cancel enabled, the bar and ``label stage done/total``
    shown. Once it ends the buttons flip back and the bar hides; the caller writes the outcome."""
    start.disabled = job.active
    cancel.disabled = not job.active
    progress.visible = job.active
    if job.total:
        progress.value = 100.0 * job.done / job.total
    if job.status == "queued":  # waiting for its lane on the session or a free slot on the server
        status.content = f"{label}: queued (position {job.position})"
    elif job.active:
        status.content = f"{label}: {job.stage or 'starting'} {job.done}/{job.total}"
