"""Background jobs: long engine work runs in a thread and reports progress; anyone may cancel it.

A job is a function ``work(progress, cancel) -> dict``: it calls ``progress(stage, done, total)``
as it goes and polls ``cancel()`` between steps, raising :class:`slam6d.errors.Cancelled` when it
turns true (the engine's own convention, so an engine call stopped inside a job ends it as cancelled). Jobs of one session
run one at a time, because they all edit the same poses; the table keeps finished jobs so a
browser that reconnects can still see how the last run ended.
"""

from __future__ import annotations

import threading
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from app.errors import JobConflictError, PartialResultError
from slam6d.errors import Cancelled, Slam6dError

Progress = Callable[[str, int, int], None]
Cancel = Callable[[], bool]
Work = Callable[[Progress, Cancel], dict[str, Any]]


@dataclass
class Job:
    id: str
    session_id: str
    kind: str
    author: str
    parameters: dict[str, Any]
    status: str = "queued"  # queued | running | done | failed | cancelled
    stage: str = ""
    done: int = 0
    total: int = 0
    message: str = ""
    result: dict[str, Any] = field(default_factory=dict)
    created: float = field(default_factory=time.time)
    finished: float | None = None
    _cancel: threading.Event = field(default_factory=threading.Event, repr=False)
    _ended: threading.Event = field(default_factory=threading.Event, repr=False)  # recorded and announced

    @property
    def active(self) -> bool:
        return self.status in ("queued", "running")

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "session_id": self.session_id,
            "kind": self.kind,
            "author": self.author,
            "parameters": self.parameters,
            "status": self.status,
            "stage": self.stage,
            "done": self.done,
            "total": self.total,
            "fraction": (self.done / self.total) if self.total else (1.0 if self.status == "done" else 0.0),
            "message": self.message,
            "result": self.result,
            "cancel_requested": self._cancel.is_set(),
            "created": self.created,
            "finished": self.finished,
        }


# Finished jobs kept in memory for browsers that reconnect; older ones are pruned (the journal keeps them).
KEEP_FINISHED = 200


class JobManager:
    """Runs jobs on threads. ``record(job, event)`` is told when a job starts and ends ("started",
    "finished"), so the workbench can journal them and find jobs a crash cut short."""

    def __init__(self, record: Callable[[Job, str], None] | None = None) -> None:
        self._jobs: dict[str, Job] = {}
        self._lock = threading.Lock()
        self._record = record
        self._listeners: list[Callable[[Job], None]] = []

    def on_change(self, listener: Callable[[Job], None]) -> None:
        """Called (from the job's thread) whenever a job's progress or status changes."""
        self._listeners.append(listener)

    def _notify(self, job: Job) -> None:
        for listener in self._listeners:
            try:
                listener(job)
            except Exception:  # a broken view must not kill the job
                traceback.print_exc()

    def submit(
        self,
        session_id: str,
        kind: str,
        work: Work,
        author: str = "anonymous",
        parameters: dict[str, Any] | None = None,
    ) -> Job:
        with self._lock:
            if any(j.session_id == session_id and j.active for j in self._jobs.values()):
                raise JobConflictError(f"a job is already running on session '{session_id}'")
            # unique across restarts: the journal may still hold the ids of an earlier process
            job = Job(f"job-{uuid.uuid4().hex[:12]}", session_id, kind, author, dict(parameters or {}))
            self._jobs[job.id] = job
            finished = [j for j in self._jobs.values() if not j.active]
            for old in sorted(finished, key=lambda j: j.finished or 0.0)[: max(0, len(finished) - KEEP_FINISHED)]:
                del self._jobs[old.id]
        if self._record is not None:
            self._record(job, "started")
        thread = threading.Thread(target=self._run, args=(job, work), name=job.id, daemon=True)
        thread.start()
        return job

    def _run(self, job: Job, work: Work) -> None:
        last_notify = 0.0

        def progress(stage: str, done: int, total: int) -> None:
            nonlocal last_notify
            job.stage, job.done, job.total = stage, int(done), int(total)
            now = time.monotonic()
            if now - last_notify > 0.05 or done >= total:  # at most ~20 view updates a second
                last_notify = now
                self._notify(job)

        job.status = "running"
        self._notify(job)
        try:
            job.result = work(progress, job._cancel.is_set) or {}
            job.status = "done"
        except Exception as exc:
            if isinstance(exc, PartialResultError):  # failed, but what it did is kept: say where
                job.result = dict(exc.result)
            if job._cancel.is_set() or isinstance(exc, Cancelled):
                job.status, job.message = "cancelled", str(exc) if isinstance(exc, PartialResultError) else "cancelled"
            else:
                job.status = "failed"
                job.message = str(exc) if isinstance(exc, Slam6dError) else f"{type(exc).__name__}: {exc}"
                if not isinstance(exc, Slam6dError):
                    traceback.print_exc()
        job.finished = time.time()
        if self._record is not None:
            self._record(job, "finished")
        self._notify(job)
        job._ended.set()

    def get(self, job_id: str) -> Job | None:
        return self._jobs.get(job_id)

    def cancel(self, job_id: str) -> Job | None:
        job = self._jobs.get(job_id)
        if job is not None and job.active:
            job._cancel.set()
            self._notify(job)
        return job

    def for_session(self, session_id: str) -> list[Job]:
        return [j for j in self._jobs.values() if j.session_id == session_id]

    def wait(self, job_id: str, timeout: float = 30.0) -> Job:
        """Block until the job ends (tests and the command line use this)."""
        job = self._jobs[job_id]
        job._ended.wait(timeout)  # past its journal record too, not only its final status
        return job
