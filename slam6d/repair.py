"""Checking a session when a server starts: repair what can be repaired, say why the rest cannot open.

A server that was killed, or a session written by an older version, can leave: a journal SQLite
cannot vouch for, a head revision whose poses are not rigid, a camera path with keyframes that
cannot be rendered, and jobs that were running when the process died. :func:`check_session` looks
at one session folder and

- refuses it (``error``) when its ``session.toml`` cannot be read or the journal fails
  ``PRAGMA integrity_check`` - nothing is written then, and the other sessions still open;
- stores a ``repair`` revision when the head's poses are not rigid (each bad pose replaced by the
  nearest rigid one, or by its last rigid predecessor when it is not finite) - history is never
  rewritten, older revisions stay as they were;
- saves the camera path again without the keyframes that cannot be rendered;
- marks every job the journal saw start but never end as ``interrupted``, with the revision it
  started from, so it is shown as such instead of vanishing.

Each repair is journaled with the author ``repair`` and listed in the result.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.errors import InvalidValueError, Slam6dError
from slam6d.geometry import Matrix, check_rigid, nearest_rotation
from slam6d.journal import JournalEntry, check_journal_file
from slam6d.session import JOURNAL_FILE, Session

# Journal entries of background jobs (written by the workbench): parameters hold ``id``, ``event``
# ("started" when accepted, "running" when a queued job begins, "finished" or "interrupted"), the job
# ``kind``, the ``revision`` it started from and, once ended, its ``status``.
JOB_ENTRY = "job"
# a job's last record says it had not ended: accepted (and maybe queued), or begun after waiting
UNFINISHED_JOB_EVENTS = ("started", "running")
REPAIR_AUTHOR = "repair"


@dataclass
class SessionCheck:
    """What :func:`check_session` found: repairs made, and the reason the session cannot open, if any."""

    folder: Path
    repaired: list[str] = field(default_factory=list)
    error: str | None = None


def check_session(folder: Path) -> SessionCheck:
    result = SessionCheck(folder)
    if (folder / JOURNAL_FILE).exists():  # before opening: opening writes to the journal
        problems = check_journal_file(folder / JOURNAL_FILE)
        fatal = [p for p in problems if not p.startswith("revision ")]
        if fatal:
            result.error = f"journal cannot be trusted: {'; '.join(fatal[:3])}"
            return result
    try:
        session = Session.open(folder)
    except Slam6dError as exc:
        result.error = str(exc)
        return result
    try:
        result.repaired += _repair_head(session)
        result.repaired += _repair_camera_path(session)
        result.repaired += mark_interrupted_jobs(session)
    except Slam6dError as exc:
        result.error = str(exc)
    return result


def _repair_head(session: Session) -> list[str]:
    head = session.journal.head
    if head is None:
        return []
    revision = session.journal.revision(head)
    if revision is None:
        return []
    fixed, notes = [], []
    for index, pose in enumerate(revision.poses):
        try:
            fixed.append(check_rigid(pose, f"poses[{index}]"))
        except InvalidValueError as exc:
            fixed.append(_nearest_rigid(pose, _last_rigid(session, revision.parent, index)))
            notes.append(exc.reason)
    if not notes:
        return []
    number = session.journal.commit(fixed, REPAIR_AUTHOR, "repair", {"from": head, "reasons": notes[:20]})
    return [f"revision {head}: {len(notes)} pose(s) not rigid, replaced by the nearest rigid ones in revision {number}"]


def _last_rigid(session: Session, parent: int | None, index: int) -> Matrix:
    while parent is not None:
        revision = session.journal.revision(parent)
        if revision is None:
            break
        try:
            return check_rigid(revision.poses[index])
        except (InvalidValueError, IndexError):
            parent = revision.parent
    return np.eye(4)


def _nearest_rigid(pose: Matrix, fallback: Matrix) -> Matrix:
    """The rigid transform closest to ``pose`` (SVD of its rotation part), or ``fallback`` when the
    pose holds no usable numbers."""
    matrix = np.asarray(pose, dtype=np.float64)
    if not np.isfinite(matrix).all() or np.abs(matrix[:3, 3]).max() > 1e7:
        return fallback
    out = np.eye(4)
    out[:3, :3] = nearest_rotation(matrix[:3, :3])
    out[:3, 3] = matrix[:3, 3]
    try:
        return check_rigid(out)
    except InvalidValueError:  # a zero matrix has no nearest rotation
        return fallback


def _repair_camera_path(session: Session) -> list[str]:
    problems = session.camera_path_problems()
    if not problems:
        return []
    session.set_camera_path(session.camera_path(), REPAIR_AUTHOR)
    return [f"camera path: {len(problems)} keyframe(s) that cannot be rendered removed ({problems[0]})"]


def job_records(entries: list[JournalEntry]) -> dict[str, dict[str, Any]]:
    """The last known state of every job the journal recorded, by job id."""
    jobs: dict[str, dict[str, Any]] = {}
    for entry in entries:
        if entry.kind != JOB_ENTRY or not isinstance(entry.parameters.get("id"), str):
            continue
        record = jobs.setdefault(entry.parameters["id"], {"author": entry.author, "started": entry.time})
        record.update(entry.parameters)
        record["time"] = entry.time
    return jobs


def mark_interrupted_jobs(session: Session) -> list[str]:
    """Journal every job that started but never ended as interrupted; one line per job."""
    notes = []
    for job_id, record in job_records(session.journal.entries()).items():
        if record.get("event") not in UNFINISHED_JOB_EVENTS:
            continue
        session.journal.append(
            REPAIR_AUTHOR,
            JOB_ENTRY,
            {
                "id": job_id,
                "event": "interrupted",
                "kind": record.get("kind"),
                "status": "interrupted",
                "revision": record.get("revision"),
            },
        )
        notes.append(f"job {job_id} ({record.get('kind')}) was interrupted; it had started from revision "
                     f"{record.get('revision')}")  # fmt: skip
    return notes
