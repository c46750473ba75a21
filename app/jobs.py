"""Background jobs: long engine work runs in a thread and reports progress; anyone may cancel it.

A job is a function ``work(progress, cancel) -> dict``: it calls ``progress(stage, done, total)``
as it goes and polls ``cancel()`` between steps, raising :class:`slam6d.errors.Cancelled` when it
turns true (the engine's own convention, so an engine call stopped inside a job ends it as cancelled).

Jobs are bounded, and queued rather than refused beyond the bounds:

* per session, one job per *lane* runs at a time (:func:`lane_of`): jobs that edit the poses
  (registration, relaxation, loop detection and closing) share the ``poses`` lane, because each
  works from the head and commits onto it; a render only reads, so it has a lane of its own and
  runs beside a relaxation; a reload (re-reading the scans) has the ``read`` lane;
* at most ``max_running`` jobs run at once over all sessions (each is CPU-bound engine work: more
  than the machine has cores only makes every one slower);
* a session holds at most :data:`MAX_QUEUED_PER_SESSION` waiting jobs (a client looping on "start"
  would otherwise grow the queue without end): past it a new job is refused with 409.

A job waits as ``queued`` with its ``position`` in the queue (1 = next), starts in submission
order once its lane and a global slot are free, and may be cancelled while it waits. A job that
ends in any way (done, failed, cancelled) frees its slot for the next. The table keeps finished
jobs so a browser that reconnects can still see how the last run ended.
"""

from __future__ import annotations

import os
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
    position: int | None = None  # 1-based place in the queue while queued
    waited: bool = False  # queued behind others before it ran
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
            "position": self.position if self.status == "queued" else None,
            "lane": lane_of(self.kind),
            "cancel_requested": self._cancel.is_set(),
            "created": self.created,
            "finished": self.finished,
        }


# Finished jobs kept in memory for browsers that reconnect; older ones are pruned (the journal keeps them).
KEEP_FINISHED = 200
MAX_QUEUED_PER_SESSION = 16

# job kind -> the lane it takes on its session; every other kind edits the poses
_LANES = {"render": "render", "reload": "read"}
POSES_LANE = "poses"


def lane_of(kind: str) -> str:
    """The per-session lane a job of ``kind`` runs in: one job per lane and session at a time."""
    return _LANES.get(kind, POSES_LANE)


def default_job_limit() -> int:
    """Jobs run at once by default: one per core (at least two, so a render need not wait for a relaxation)."""
    return max(2, os.cpu_count() or 1)


class JobManager:
    """Runs jobs on threads, queued beyond the limits above. ``record(job, event)`` is told when a job
    is accepted ("started"), when a queued one begins ("running") and when it ends ("finished"), so
    the workbench can journal them and find jobs a crash cut short."""

    def __init__(self, record: Callable[[Job, str], None] | None = None, max_running: int | None = None) -> None:
        if max_running is not None and max_running < 1:
            raise ValueError(f"max_running must be at least 1, got {max_running}")
        self.max_running = max_running or default_job_limit()
        self._jobs: dict[str, Job] = {}
        self._queue: list[Job] = []  # waiting jobs, oldest first
        self._work: dict[str, Work] = {}  # what each waiting job will run
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
        """Accept a job: it runs at once when its lane and a global slot are free, else it is queued."""
        with self._lock:
            waiting = sum(1 for j in self._queue if j.session_id == session_id)
            if waiting >= MAX_QUEUED_PER_SESSION:
                raise JobConflictError(
                    f"session '{session_id}' already has {waiting} jobs queued; wait for them or cancel some"
                )
            # unique across restarts: the journal may still hold the ids of an earlier process
            job = Job(f"job-{uuid.uuid4().hex[:12]}", session_id, kind, author, dict(parameters or {}))
            self._jobs[job.id] = job
            finished = [j for j in self._jobs.values() if not j.active]
            for old in sorted(finished, key=lambda j: j.finished or 0.0)[: max(0, len(finished) - KEEP_FINISHED)]:
                del self._jobs[old.id]
        if self._record is not None:  # journaled before it can run: its end is never recorded before its start
            self._record(job, "started")
        with self._lock:
            self._queue.append(job)
            self._work[job.id] = work
            job.position = len(self._queue)
        self._dispatch()
        return job

    def _dispatch(self) -> None:
        """Start every queued job, oldest first, whose lane on its session and a global slot are free."""
        starting: list[tuple[Job, Work]] = []
        with self._lock:
            running = [j for j in self._jobs.values() if j.status == "running"]
            busy = {(j.session_id, lane_of(j.kind)) for j in running}
            slots = self.max_running - len(running)
            for job in list(self._queue):
                lane = (job.session_id, lane_of(job.kind))
                if slots <= 0:
                    break
                if lane in busy:
                    continue
                self._queue.remove(job)
                job.status, job.position = "running", None
                busy.add(lane)
                slots -= 1
                starting.append((job, self._work.pop(job.id)))
            for place, job in enumerate(self._queue, start=1):
                job.waited, job.position = True, place
            queued = list(self._queue)
        for job, work in starting:
            threading.Thread(target=self._run, args=(job, work), name=job.id, daemon=True).start()
        for job in queued:  # their positions may have moved
            self._notify(job)

    def _run(self, job: Job, work: Work) -> None:
        last_notify = 0.0

        def progress(stage: str, done: int, total: int) -> None:
            nonlocal last_notify
            job.stage, job.done, job.total = stage, int(done), int(total)
            now = time.monotonic()
            if now - last_notify > 0.05 or done >= total:  # at most ~20 view updates a second
                last_notify = now
                self._notify(job)

        if job.waited and self._record is not None:  # the revision it really starts from
            self._record(job, "running")
        self._notify(job)
        try:
            if job._cancel.is_set():
                raise Cancelled("cancelled")
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
        finally:
            self._end(job)

    def _end(self, job: Job) -> None:
        """A job has its final status: journal and announce it, then give its slot to the next."""
        job.finished = time.time()
        try:
            if self._record is not None:
                self._record(job, "finished")
            self._notify(job)
        finally:
            job._ended.set()
            self._dispatch()

    def get(self, job_id: str) -> Job | None:
        return self._jobs.get(job_id)

    def cancel(self, job_id: str) -> Job | None:
        """Ask a running job to stop at its next check; a queued one ends as cancelled at once."""
        job = self._jobs.get(job_id)
        if job is None or not job.active:
            return job
        job._cancel.set()
        with self._lock:
            dequeued = job in self._queue
            if dequeued:
                self._queue.remove(job)
                self._work.pop(job.id, None)
                job.status, job.message, job.position = "cancelled", "cancelled while queued", None
        if dequeued:
            self._end(job)
        else:
            self._notify(job)
        return job

    def for_session(self, session_id: str) -> list[Job]:
        return [j for j in self._jobs.values() if j.session_id == session_id]

    def busy_sessions(self) -> set[str]:
        """Sessions with a job running or queued (their loaded scans must stay in memory)."""
        return {j.session_id for j in list(self._jobs.values()) if j.active}

    def wait(self, job_id: str, timeout: float = 30.0) -> Job:
        """Block until the job ends (tests and the command line use this)."""
        job = self._jobs[job_id]
        job._ended.wait(timeout)  # past its journal record too, not only its final status
        return job
