"""The workbench's shared state: which sessions exist, their loaded scans, and who is told of edits.

Every edit - from a REST call, a button in the 3D view or a background job - goes through
:class:`Workbench`, which writes the journal and then tells the listeners (the 3D views), so all
browsers on a session show the same revision.
"""

from __future__ import annotations

import logging
import re
import shutil
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from app.data_root import DataRoot
from app.errors import EditError, ParseTimeoutError, UnknownSessionError
from app.jobs import Job, JobManager
from app.resources import Loaded, ResourceLimits, SessionMemory, array_bytes
from app.upload import UploadLimits, check_parses, session_from_upload
from slam6d.errors import SessionError, Slam6dError
from slam6d.geometry import Matrix
from slam6d.journal import Change, Revision, StaleRevisionError
from slam6d.repair import JOB_ENTRY, UNFINISHED_JOB_EVENTS, SessionCheck, check_session, job_records
from slam6d.scan import ScanSequence
from slam6d.scheduler import Scheduler, local_workers, open_scheduler
from slam6d.session import SESSION_FILE, Session, reserve_session_folder

log = logging.getLogger("slam6d.workbench")
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


@dataclass
class SessionState:
    """A session with its scans loaded once and kept at the current revision's poses (until the
    memory budget releases them: the next :meth:`sequence` reads them again)."""

    session: Session
    lock: threading.RLock = field(default_factory=threading.RLock)
    _sequence: ScanSequence | None = None
    last_used: float = field(default_factory=time.monotonic)
    on_load: Callable[[], object] | None = None  # told after the scans were read (the budget is checked)
    on_release: Callable[[], None] | None = None  # told when they are let go
    parse_timeout_s: float | None = None

    def sequence(self, progress: Callable[[int, int], None] | None = None) -> ScanSequence:
        self.last_used = time.monotonic()
        with self.lock:
            sequence, fresh = self._sequence, self._sequence is None
            if sequence is None:
                sequence = self._sequence = self._load(progress)
        if fresh and self.on_load is not None:
            self.on_load()
        return sequence

    def _load(self, progress: Callable[[int, int], None] | None) -> ScanSequence:
        """Read the scans, giving up between files once ``parse_timeout_s`` has passed (naming the file
        it was at): a session over a folder of huge or slow files fails its job instead of holding it."""
        if self.parse_timeout_s is None:
            return self.session.load_sequence(progress)
        deadline = time.monotonic() + self.parse_timeout_s
        files = self.session.scan_files()
        limit = self.parse_timeout_s

        def timed(done: int, total: int) -> None:
            if time.monotonic() > deadline and done < total:
                at = files[done].name if done < len(files) else f"scan {done}"
                raise ParseTimeoutError(f"reading the scans took longer than {limit:g} s; stopped before {at}")
            if progress is not None:
                progress(done, total)

        return self.session.load_sequence(timed)

    @property
    def loaded(self) -> bool:
        return self._sequence is not None

    def held_bytes(self) -> int:
        """The scans' arrays in memory (an estimate of what releasing them frees)."""
        sequence = self._sequence
        if sequence is None:
            return 0
        return array_bytes(a for scan in sequence.scans for a in (scan.points, scan.intensity))

    def release(self) -> bool:
        """Let the scans go (the journal stays open); False when someone holds the lock (busy)."""
        if not self.lock.acquire(blocking=False):
            return False
        try:
            if self._sequence is None:
                return False
            self._sequence = None
        finally:
            self.lock.release()
        if self.on_release is not None:
            self.on_release()
        return True

    def apply_head(self) -> None:
        """Move the loaded scans to the journal's current revision."""
        with self.lock:
            if self._sequence is not None:
                for scan, pose in zip(self._sequence.scans, self.session.poses(), strict=True):
                    scan.pose = pose


class Workbench:
    def __init__(
        self,
        sessions_dir: Path | str,
        max_upload_bytes: int = 512 * 1024 * 1024,
        data_root: DataRoot | None = None,
        limits: ResourceLimits | None = None,
        scheduler: str | None = None,
    ) -> None:
        """``scheduler``: where the jobs that support it (registration, relaxation) run their parallel
        stages, as ``slam6d run --scheduler`` takes it (``local:N``, ``tcp://HOST:PORT``); None: here."""
        if scheduler is not None:
            local_workers(scheduler)  # a bad address is refused at start, not at the first job
        self.scheduler_spec = scheduler
        self._scheduler: Scheduler | None = None
        self._scheduler_lock = threading.Lock()
        self.sessions_dir = Path(sessions_dir)
        self.data_root = data_root or DataRoot(None, shared=False)
        self.sessions_dir.mkdir(parents=True, exist_ok=True)
        self.max_upload_bytes = max_upload_bytes
        self.limits = limits or ResourceLimits()
        self.jobs = JobManager(record=self._record_job, max_running=self.limits.max_jobs)
        self._states: dict[str, SessionState] = {}
        self._lock = threading.Lock()
        # besides a job, what keeps a session's scans in memory (the 3D views add theirs)
        self.in_use_checks: list[Callable[[str], bool]] = []
        self._release_listeners: list[Callable[[str], None]] = []
        self.memory = SessionMemory(self.limits.session_memory_bytes, self._in_use)
        self.jobs.on_change(self._job_changed)
        self._revision_listeners: list[Callable[[str], None]] = []
        self._camera_path_listeners: list[Callable[[str], None]] = []
        self.checks: dict[str, SessionCheck] = {}
        self.check_sessions()

    def check_sessions(self) -> dict[str, SessionCheck]:
        """Check (and repair) every session once, at start: what was repaired is logged and listed
        with the session; a session that cannot open says why, and the others open as usual."""
        for session_id in self.session_ids():
            check = check_session(self.sessions_dir / session_id)
            self.checks[session_id] = check
            for note in check.repaired:
                log.warning("session %s repaired: %s", session_id, note)
            if check.error:
                log.error("session %s cannot open: %s", session_id, check.error)
        return self.checks

    def scheduler(self) -> Scheduler | None:
        """The engine's scheduler (:mod:`slam6d.scheduler`) for the jobs, opened at the first job that asks
        and then shared by all (a ``local:N`` cluster starts once); None without ``--scheduler``, so
        nothing of Dask is started or imported."""
        if self.scheduler_spec is None:
            return None
        with self._scheduler_lock:
            if self._scheduler is None:
                self._scheduler = open_scheduler(self.scheduler_spec)
            return self._scheduler

    def close_scheduler(self) -> None:
        """Close the scheduler's client (and the local cluster it started) when the server stops."""
        with self._scheduler_lock:
            if self._scheduler is not None:
                self._scheduler.close()
                self._scheduler = None

    def _record_job(self, job: Job, event: str) -> None:
        """Journal a job's start and end, so one cut short by a crash is found and shown after a restart."""
        try:
            session = self.state(job.session_id).session
            parameters: dict[str, Any] = {"id": job.id, "event": event, "kind": job.kind, "status": job.status}
            if event in ("started", "running"):  # accepted, and (after waiting in the queue) begun
                parameters["revision"] = session.journal.head
            elif job.message:
                parameters["message"] = job.message[:500]
            session.journal.append(job.author, JOB_ENTRY, parameters)
        except Exception:  # the job itself must not fail because its record could not be written
            log.exception("could not journal job %s (%s)", job.id, event)

    def recorded_job(self, job_id: str) -> dict[str, Any] | None:
        """A job no longer (or never) in memory, as the journals last recorded it: an interrupted job
        answers with the revision it started from instead of vanishing after a restart."""
        for session_id in self.session_ids():
            try:
                entries = self.state(session_id).session.journal.entries()
            except Exception:
                continue
            record = job_records(entries).get(job_id)
            if record is not None:
                unfinished = record.get("event") in UNFINISHED_JOB_EVENTS
                status = "interrupted" if unfinished else record.get("status", "interrupted")
                return {**record, "id": job_id, "session_id": session_id, "status": status, "from_journal": True}
        return None

    # -------------------------------------------------------------- sessions

    def on_revision(self, listener: Callable[[str], None]) -> None:
        """``listener(session_id)`` runs after every change of a session's current revision."""
        self._revision_listeners.append(listener)

    def _changed(self, session_id: str) -> None:
        """Tell everyone the head moved. The change is already in the journal: a view that fails to
        follow is logged, never turned into an error answer (a client told "409" after its redo was
        applied would retry and apply it twice)."""
        steps: list[Callable[[], None]] = [self.state(session_id).apply_head]
        steps += [partial(listener, session_id) for listener in self._revision_listeners]
        for step in steps:
            try:
                step()
            except Exception:
                log.exception("after a change of session %s, a view failed to follow", session_id)

    def on_camera_path(self, listener: Callable[[str], None]) -> None:
        """``listener(session_id)`` runs after a session's saved camera path changed (from any browser or REST)."""
        self._camera_path_listeners.append(listener)

    def camera_path_changed(self, session_id: str) -> None:
        for listener in self._camera_path_listeners:
            listener(session_id)

    def notify(self, session_id: str) -> None:
        """Tell the views a session changed without a new revision (e.g. new loop hypotheses to review)."""
        self._changed(session_id)

    def session_ids(self) -> list[str]:
        return sorted(p.name for p in self.sessions_dir.iterdir() if (p / SESSION_FILE).is_file() and _ID.match(p.name))

    def state(self, session_id: str) -> SessionState:
        if not _ID.match(session_id) or not (self.sessions_dir / session_id / SESSION_FILE).is_file():
            raise UnknownSessionError(session_id)
        check = self.checks.get(session_id)
        if check is not None and check.error:
            raise SessionError(self.sessions_dir / session_id, f"cannot be opened: {check.error}")
        with self._lock:
            state = self._states.get(session_id)
            if state is None:
                state = self._states[session_id] = SessionState(
                    Session.open(self.sessions_dir / session_id),
                    on_load=self.enforce_memory_budget,
                    on_release=partial(self._released, session_id),
                    parse_timeout_s=self.limits.parse_timeout_s,
                )
        return state  # its scans' last use (what the budget orders by) is stamped by SessionState.sequence

    # -------------------------------------------------------------- memory

    def _in_use(self, session_id: str) -> bool:
        return session_id in self.jobs.busy_sessions() or any(check(session_id) for check in self.in_use_checks)

    def on_release(self, listener: Callable[[str], None]) -> None:
        """``listener(session_id)`` runs after the memory budget released a session's scans (drop what
        was derived from them)."""
        self._release_listeners.append(listener)

    def _released(self, session_id: str) -> None:
        for listener in self._release_listeners:
            listener(session_id)

    def _job_changed(self, job: Job) -> None:
        if not job.active:  # the session it held may now be let go
            self.enforce_memory_budget()

    def enforce_memory_budget(self) -> list[str]:
        """Release least recently used idle sessions' scans while the opened ones exceed the budget."""
        with self._lock:
            states: dict[str, Loaded] = dict(self._states)
        return self.memory.enforce(states)

    def summary(self, session_id: str) -> dict[str, Any]:
        """What the landing page lists; a broken session is listed with its error rather than hidden."""
        try:
            session = self.state(session_id).session
            return {
                "id": session_id,
                "name": session.name,
                "scans": len(session.scan_files()),
                "revision": session.revision,
                "format": session.config.format_name,
                "error": None,
                "repaired": self._repaired(session_id),
            }
        except Slam6dError as exc:
            return {
                "id": session_id,
                "name": session_id,
                "scans": 0,
                "revision": 0,
                "format": "",
                "error": str(exc),
                "repaired": self._repaired(session_id),
            }

    def _repaired(self, session_id: str) -> list[str]:
        check = self.checks.get(session_id)
        return list(check.repaired) if check is not None else []

    def create_from_folder(
        self, name: str, source: Path, format_name: str | None = None, frame: str | None = None
    ) -> Session:
        source = self.data_root.check(source)  # before anything looks at the path
        folder = reserve_session_folder(self.sessions_dir, name)
        try:
            session = Session.create(folder, name, source, format_name, frame)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        return session

    def create_from_upload(
        self,
        name: str,
        files: Iterable[tuple[str, BinaryIO]],
        format_name: str | None = None,
        frame: str | None = None,
    ) -> Session:
        """A new session of uploaded scan files (or .zips of them), every scan proven to parse
        (:func:`app.upload.session_from_upload`); a refused upload leaves nothing behind."""
        limits = UploadLimits(self.max_upload_bytes, self.limits.parse_timeout_s)
        return session_from_upload(self.sessions_dir, name, files, limits, format_name, frame)

    def check_imported(self, session: Session, label: str) -> Session:
        """Parse an imported session's scans as an upload's are (same time limit); on any problem the
        session folder is removed, so a refused import leaves nothing behind."""
        return check_parses(session, self.limits.parse_timeout_s, label)

    # -------------------------------------------------------------- edits

    def commit(
        self,
        session_id: str,
        poses: list[Matrix],
        author: str,
        kind: str,
        parameters: dict[str, Any] | None = None,
        graph: dict[str, Any] | None = None,
        base: int | None = None,
    ) -> int:
        """Poses for every scan as a new revision; with ``base`` (the revision they were computed
        from) only the scans that differ from it are laid onto the head, or EditConflictError (409)
        names the edit that moved one of them meanwhile."""
        rev = self.state(session_id).session.journal.commit(poses, author, kind, parameters, graph, base)
        self._changed(session_id)
        return rev

    def apply(
        self, session_id: str, change: Change, author: str, kind: str, parameters: dict[str, Any] | None = None
    ) -> int:
        """One edit (some scans' poses, a change of the graph) applied to the head as a new revision."""
        rev = self.state(session_id).session.journal.apply(change, author, kind, parameters)
        self._changed(session_id)
        return rev

    def undo(self, session_id: str, author: str, revision: int | None = None) -> int:
        """Step back from ``revision`` (default: the head); EditError (409) when there is nothing to undo.

        Naming the revision makes a retry safe: undoing it again answers where the first undo went.
        """
        return self._step(session_id, "undo", author, revision)

    def redo(self, session_id: str, author: str, revision: int | None = None) -> int:
        """Step forward from ``revision`` (default: the head); EditError (409) when there is nothing to redo."""
        return self._step(session_id, "redo", author, revision)

    def _step(self, session_id: str, direction: str, author: str, revision: int | None) -> int:
        journal = self.state(session_id).session.journal
        step = journal.undo if direction == "undo" else journal.redo
        try:
            rev = step(author, revision)
        except StaleRevisionError:
            raise
        except SessionError as exc:
            raise EditError(str(exc)) from None
        self._changed(session_id)
        return rev

    def head(self, session_id: str) -> Revision:
        """The current revision (number, poses, graph) read at once, for an edit to name as its base."""
        return self.state(session_id).session.get_revision()

    def current_poses(self, session_id: str) -> list[Matrix]:
        return [np.asarray(p) for p in self.state(session_id).session.poses()]


__all__ = ["SessionState", "Workbench"]
