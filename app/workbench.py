"""The workbench's shared state: which sessions exist, their loaded scans, and who is told of edits.

Every edit - from a REST call, a button in the 3D view or a background job - goes through
:class:`Workbench`, which writes the journal and then tells the listeners (the 3D views), so all
browsers on a session show the same revision.
"""

from __future__ import annotations

import io
import re
import shutil
import threading
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from app.errors import EditError, UnknownSessionError, UploadError
from app.jobs import JobManager
from slam6d.errors import SessionError, Slam6dError
from slam6d.geometry import Matrix
from slam6d.scan import ScanSequence
from slam6d.session import SESSION_FILE, Session

_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_UPLOAD_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,199}$")


@dataclass
class SessionState:
    """A session with its scans loaded once and kept at the current revision's poses."""

    session: Session
    lock: threading.RLock = field(default_factory=threading.RLock)
    _sequence: ScanSequence | None = None

    def sequence(self, progress: Callable[[int, int], None] | None = None) -> ScanSequence:
        with self.lock:
            if self._sequence is None:
                self._sequence = self.session.load_sequence(progress)
            return self._sequence

    @property
    def loaded(self) -> bool:
        return self._sequence is not None

    def apply_head(self) -> None:
        """Move the loaded scans to the journal's current revision."""
        with self.lock:
            if self._sequence is not None:
                for scan, pose in zip(self._sequence.scans, self.session.poses(), strict=True):
                    scan.pose = pose


def slugify(name: str) -> str:
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-._")[:60]
    return slug or "session"


class Workbench:
    def __init__(self, sessions_dir: Path | str, max_upload_bytes: int = 512 * 1024 * 1024) -> None:
        self.sessions_dir = Path(sessions_dir)
        self.sessions_dir.mkdir(parents=True, exist_ok=True)
        self.max_upload_bytes = max_upload_bytes
        self.jobs = JobManager()
        self._states: dict[str, SessionState] = {}
        self._lock = threading.Lock()
        self._revision_listeners: list[Callable[[str], None]] = []
        self._camera_path_listeners: list[Callable[[str], None]] = []

    # -------------------------------------------------------------- sessions

    def on_revision(self, listener: Callable[[str], None]) -> None:
        """``listener(session_id)`` runs after every change of a session's current revision."""
        self._revision_listeners.append(listener)

    def _changed(self, session_id: str) -> None:
        self.state(session_id).apply_head()
        for listener in self._revision_listeners:
            listener(session_id)

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
        with self._lock:
            if session_id not in self._states:
                self._states[session_id] = SessionState(Session.open(self.sessions_dir / session_id))
            return self._states[session_id]

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
            }
        except Slam6dError as exc:
            return {"id": session_id, "name": session_id, "scans": 0, "revision": 0, "format": "", "error": str(exc)}

    def _new_folder(self, name: str) -> Path:
        base = slugify(name)
        candidate, n = base, 1
        while (self.sessions_dir / candidate).exists():
            n += 1
            candidate = f"{base}-{n}"
        return self.sessions_dir / candidate

    def create_from_folder(
        self, name: str, source: Path, format_name: str | None = None, frame: str | None = None
    ) -> Session:
        source = Path(source).expanduser().resolve()
        folder = self._new_folder(name)
        try:
            session = Session.create(folder, name, source, format_name, frame)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        return session

    def create_from_upload(
        self, name: str, files: Iterable[tuple[str, bytes]], format_name: str | None = None, frame: str | None = None
    ) -> Session:
        """Store uploaded scan files (or a .zip of them) in a new session and prove they all parse.

        On any problem the half-made folder is removed: a refused upload leaves nothing behind.
        """
        folder = self._new_folder(name)
        scans = folder / "scans"
        try:
            scans.mkdir(parents=True)
            total = 0
            for filename, content in files:
                for member, data in _expand(filename, content, self.max_upload_bytes):
                    total += len(data)
                    if total > self.max_upload_bytes:
                        raise UploadError(f"upload exceeds the limit of {self.max_upload_bytes // 2**20} MiB", 413)
                    if (scans / member).exists():
                        raise UploadError(f"file '{member}' appears twice in the upload")
                    (scans / member).write_bytes(data)
            if total == 0:
                raise UploadError("the upload contains no files")
            session = Session.create(folder, name, "scans", format_name, frame)
            session.load_sequence()  # parses every scan: a bad file is reported now, with its name and line
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        return session

    # -------------------------------------------------------------- edits

    def commit(
        self,
        session_id: str,
        poses: list[Matrix],
        author: str,
        kind: str,
        parameters: dict[str, Any] | None = None,
        graph: dict[str, Any] | None = None,
    ) -> int:
        rev = self.state(session_id).session.journal.commit(poses, author, kind, parameters, graph)
        self._changed(session_id)
        return rev

    def undo(self, session_id: str, author: str) -> int:
        """Step back one revision; EditError (409) when there is nothing to undo."""
        journal = self.state(session_id).session.journal
        try:
            rev = journal.undo(author)
        except SessionError as exc:
            raise EditError(str(exc)) from None
        self._changed(session_id)
        return rev

    def redo(self, session_id: str, author: str) -> int:
        """Step forward one revision; EditError (409) when there is nothing to redo."""
        journal = self.state(session_id).session.journal
        try:
            rev = journal.redo(author)
        except SessionError as exc:
            raise EditError(str(exc)) from None
        self._changed(session_id)
        return rev

    def current_poses(self, session_id: str) -> list[Matrix]:
        return [np.asarray(p) for p in self.state(session_id).session.poses()]


def _expand(filename: str, content: bytes, limit: int) -> list[tuple[str, bytes]]:
    """Validate one uploaded file name; unpack a zip (flattening folders, refusing traversal)."""
    base = PurePosixPath(filename.replace("\\", "/")).name
    if base.lower().endswith(".zip"):
        try:
            archive = zipfile.ZipFile(io.BytesIO(content))
        except zipfile.BadZipFile:
            raise UploadError(f"'{base}' is not a valid zip archive") from None
        members = [i for i in archive.infolist() if not i.is_dir()]
        if sum(i.file_size for i in members) > limit:
            raise UploadError(f"'{base}' unpacks to more than the limit of {limit // 2**20} MiB", 413)
        out = []
        for info in members:
            parts = PurePosixPath(info.filename).parts
            if info.filename.startswith("/") or ".." in parts:
                raise UploadError(f"'{base}' contains an unsafe path '{info.filename}'")
            if parts[-1].startswith(".") or "__MACOSX" in parts:
                continue
            out.extend(_expand(parts[-1], archive.read(info), limit))
        return out
    if not _UPLOAD_NAME.match(base):
        raise UploadError(f"file name '{filename}' is not allowed (letters, digits, '.', '_', '-')")
    return [(base, content)]


__all__ = ["SessionState", "Workbench"]
