"""A session's history: an append-only SQLite journal of everything done, and the pose revisions.

Every run and edit is an entry (time, author, kind, parameters). An entry that changes poses also
stores a revision: all poses (canonical ``world_from_scan``) and the pose-graph annotations, as a
child of the revision current when it was made. The journal is never rewritten: undo and redo are
entries too, and the current revision ("head") and the redo stack are derived by replaying it, so
two processes (or browsers) that append see the same history. Each write is one ``BEGIN
IMMEDIATE`` transaction, so two writers cannot both build on the same head.

No lost update: an edit is a :class:`Change` (this scan's new pose, a function of the graph),
applied to the head *inside* that transaction - never a whole state computed from an older read
and written over the head - so two people moving different scans at once both keep their moves.
A caller that wants strictness names the revision it saw (:func:`expecting`, the HTTP
``If-Match``): if the head moved on, nothing is written and :class:`StaleRevisionError` lists the
revisions since and who made them. Work that ran for a while from an older revision (a
relaxation) gives that ``base``: its scans are laid onto the head if nobody moved them meanwhile,
and otherwise :class:`EditConflictError` names the edit that did.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import closing, contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.errors import InvalidValueError, SessionError
from slam6d.geometry import Matrix, check_rigid
from slam6d.trace import to_jsonable


@dataclass(frozen=True)
class JournalEntry:
    id: int
    time: str
    author: str
    kind: str
    parameters: dict[str, Any]
    head: int | None  # the revision current after this entry (None before revision 0 exists)
    revision: int | None  # the revision this entry created, if any


@dataclass(frozen=True)
class Revision:
    number: int
    parent: int | None
    entry_id: int
    poses: list[Matrix]
    graph: dict[str, Any]


Graph = dict[str, Any]
Document = dict[str, Any]


@dataclass(frozen=True)
class Change:
    """What one edit does to the head: new poses for some scans and/or a change of the graph.

    ``graph`` is a function of the head's graph (it runs inside the write transaction, so an edge
    added by someone else a moment ago is kept). ``base`` is the revision the change was computed
    from when that matters (a job's start): the scans in ``poses`` must not have moved since.
    """

    poses: Mapping[int, Matrix] = field(default_factory=dict)
    graph: Callable[[Graph], Graph] | None = None
    base: int | None = None


class StaleRevisionError(SessionError):
    """The caller expected another head (``If-Match``); ``since`` lists what happened after it."""

    def __init__(self, folder: Path, expected: int, head: int | None, since: list[JournalEntry]) -> None:
        self.expected = expected
        self.head = head
        self.since = since
        who = ", ".join(f"revision {e.head} ({e.kind} by {e.author})" for e in since[-5:])
        _without_folder(
            self,
            folder,
            f"the session is at revision {head}, not {expected}"
            + (f"; since then: {who}" if who else "")
            + "; nothing was changed",
        )


class EditConflictError(SessionError):
    """Work computed from an older revision touches a scan someone moved meanwhile (``entry`` did)."""

    def __init__(self, folder: Path, base: int, scans: list[int], entry: JournalEntry | None) -> None:
        self.base = base
        self.scans = scans
        self.entry = entry
        listed = ", ".join(str(k) for k in scans[:10]) + (" ..." if len(scans) > 10 else "")
        by = (
            f" by {entry.author} ({entry.kind}, revision {entry.head}, {entry.time})"
            if entry is not None
            else " meanwhile"
        )
        _without_folder(
            self,
            folder,
            f"started from revision {base}, but scan {listed} was changed{by}; nothing was changed, run it again",
        )


def _without_folder(error: SessionError, folder: Path, message: str) -> None:
    """Fill a SessionError whose message is for other users of a shared server: it names no server path."""
    error.path = folder
    error.reason = message
    Exception.__init__(error, message)


_expected_head: ContextVar[int | None] = ContextVar("expected_head", default=None)


@contextmanager
def expecting(revision: int | None) -> Iterator[None]:
    """Writes in this context (this thread or task) happen only if the head is still ``revision``.

    The web layer sets it from a request's ``If-Match``, so every write a request makes is checked
    inside its own transaction without each edit passing the revision along.
    """
    token = _expected_head.set(revision)
    try:
        yield
    finally:
        _expected_head.reset(token)


def expect_head(revision: int | None) -> None:
    """:func:`expecting` for the rest of the current context: an async request task (and the worker
    threads it hands work to, which copy the context), set where no ``with`` block spans the work."""
    _expected_head.set(revision)


def now() -> str:
    """UTC time with milliseconds, the journal's timestamp format."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class Journal:
    """One journal file. Opening creates its tables; every call opens its own short connection."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            with self._write() as conn:
                conn.execute(
                    "CREATE TABLE IF NOT EXISTS entries (id INTEGER PRIMARY KEY AUTOINCREMENT, time TEXT NOT NULL,"
                    " author TEXT NOT NULL, kind TEXT NOT NULL, parameters TEXT NOT NULL, head INTEGER,"
                    " revision INTEGER)"
                )
                conn.execute(
                    "CREATE TABLE IF NOT EXISTS revisions (number INTEGER PRIMARY KEY, parent INTEGER,"
                    " entry_id INTEGER NOT NULL, scans INTEGER NOT NULL, poses BLOB NOT NULL, graph TEXT NOT NULL)"
                )
        except sqlite3.DatabaseError as exc:  # not a journal, or damaged beyond what SQLite opens
            raise SessionError(path.parent, f"{path.name} is not a readable journal ({exc})") from None

    def _error(self, message: str) -> SessionError:
        return SessionError(self.path.parent, message)

    def _stack(self, poses: Sequence[Matrix], kind: str) -> np.ndarray:
        """The poses as one array, each checked rigid (:func:`slam6d.geometry.check_rigid`).

        A revision is kept forever, so a pose that is not rigid is refused here with an
        :class:`InvalidValueError` naming it, and nothing is written.
        """
        if not len(poses):
            raise self._error(f"refusing to store a revision without poses ({kind})")
        return np.stack([check_rigid(p, f"poses[{i}]") for i, p in enumerate(poses)])

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, timeout=30, isolation_level=None)
        conn.execute("PRAGMA journal_mode=WAL")
        return conn

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        with closing(self._connect()) as conn:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    # -------------------------------------------------------------- writing

    def append(self, author: str, kind: str, parameters: dict[str, Any] | None = None) -> JournalEntry:
        """Record something that does not change poses (a rejected loop, a setting, a failed run)."""
        with self._write() as conn:
            self._check_expected(conn)
            return _insert_entry(conn, author, kind, parameters or {}, _head_of(conn), None)

    def update_document(self, author: str, kind: str, change: Callable[[Document | None], Document]) -> JournalEntry:
        """Append the next version of a document kept in the journal (the camera path, comments).

        ``change`` gets the latest version (None before the first) inside the write transaction, so
        two keyframes added at once are both in the result.
        """
        with self._write() as conn:
            self._check_expected(conn)
            row = conn.execute(
                "SELECT parameters FROM entries WHERE kind=? ORDER BY id DESC LIMIT 1", (kind,)
            ).fetchone()
            updated = change(None if row is None else json.loads(row[0]))
            return _insert_entry(conn, author, kind, updated, _head_of(conn), None)

    def latest(self, kind: str) -> JournalEntry | None:
        """The newest entry of a kind (the current version of a document)."""
        with closing(self._connect()) as conn:
            row = conn.execute(
                "SELECT id, time, author, kind, parameters, head, revision FROM entries WHERE kind=?"
                " ORDER BY id DESC LIMIT 1",
                (kind,),
            ).fetchone()
        return None if row is None else JournalEntry(row[0], row[1], row[2], row[3], json.loads(row[4]), row[5], row[6])

    def commit(
        self,
        poses: Sequence[Matrix],
        author: str,
        kind: str,
        parameters: dict[str, Any] | None = None,
        graph: dict[str, Any] | None = None,
        base: int | None = None,
    ) -> int:
        """Store poses for every scan (the first import, a whole run) as a new revision.

        Without ``graph`` the new revision keeps the head's annotations. With ``base`` (the revision
        the poses were computed from) only the scans that differ from it are laid onto the head. Every
        pose must be rigid; one that is not refuses the whole revision.
        """
        stack = self._stack(poses, kind)
        if base is None:
            changed: dict[int, Matrix] = dict(enumerate(stack))
        else:
            start = self.revision(base)
            if start is None or len(start.poses) != len(stack):
                raise self._error(f"no revision {base} with {len(stack)} scans to start from")
            changed = {k: stack[k] for k in range(len(stack)) if not np.array_equal(stack[k], start.poses[k])}
        return self.apply(
            Change(changed, None if graph is None else (lambda _head: graph), base),
            author,
            kind,
            parameters,
            scans=len(stack),
        )

    def apply(
        self,
        change: Change,
        author: str,
        kind: str,
        parameters: dict[str, Any] | None = None,
        scans: int | None = None,
    ) -> int:
        """Apply a change to the head as a new revision (its child) and make it current.

        ``scans`` is only needed for the very first revision (there is no head to take the count from).
        """
        new_poses = {int(k): check_rigid(p, f"poses[{k}]") for k, p in change.poses.items()}
        with self._write() as conn:
            self._check_expected(conn)
            parent = _head_of(conn)
            if parent is None:
                if scans is None or sorted(new_poses) != list(range(scans)):
                    raise self._error(f"the first revision needs a pose for every scan ({kind})")
                poses, graph = np.zeros((scans, 4, 4)), {}
            else:
                head = _revision_of(conn, parent)
                poses, graph = np.array(head.poses), head.graph
            for k in new_poses:
                if not 0 <= k < len(poses):
                    raise self._error(f"no scan {k}; the session has scans 0..{len(poses) - 1} ({kind})")
            if change.base is not None and parent is not None and change.base != parent:
                start = _revision_of(conn, change.base)
                moved = [k for k in sorted(new_poses) if not np.array_equal(start.poses[k], poses[k])]
                if moved:
                    raise EditConflictError(
                        self.path.parent, change.base, moved, _first_change_of(conn, change.base, moved)
                    )
            for k, pose in new_poses.items():
                poses[k] = pose
            if change.graph is not None:
                graph = change.graph(graph)
            number = int(conn.execute("SELECT COALESCE(MAX(number), -1) + 1 FROM revisions").fetchone()[0])
            entry = _insert_entry(conn, author, kind, parameters or {}, number, number)
            conn.execute(
                "INSERT INTO revisions (number, parent, entry_id, scans, poses, graph) VALUES (?,?,?,?,?,?)",
                (number, parent, entry.id, len(poses), poses.tobytes(), json.dumps(to_jsonable(graph))),
            )
        return number

    def commit_first(
        self, poses: Sequence[Matrix], author: str, kind: str, parameters: dict[str, Any] | None = None
    ) -> int:
        """Store revision 0 unless a revision exists already; the head either way.

        Two requests that both find a new session without revisions (the first view and the first
        poses, racing) would otherwise both store an "import"; the check and the insert share one
        write transaction, so exactly one does.
        """
        stack = self._stack(poses, kind)
        with self._write() as conn:
            head = _head_of(conn)
            if head is not None:
                return head
            entry = _insert_entry(conn, author, kind, parameters or {}, 0, 0)
            conn.execute(
                "INSERT INTO revisions (number, parent, entry_id, scans, poses, graph) VALUES (0,NULL,?,?,?,?)",
                (entry.id, len(stack), stack.tobytes(), json.dumps({})),
            )
        return 0

    def undo(self, author: str, revision: int | None = None) -> int:
        """Go back to the parent of the current revision (an entry of its own; nothing is deleted).

        With ``revision`` (the head the caller saw) a repeated request is answered, not repeated:
        if that revision was undone already, the answer is the revision it went back to.
        """
        with self._write() as conn:
            self._check_expected(conn)
            head = _head_of(conn)
            if revision is not None and head != revision:
                return self._repeated(conn, "undo", revision, head)
            parent = None if head is None else _revision_of(conn, head).parent
            if parent is None:
                raise self._error("nothing to undo")
            _insert_entry(conn, author, "undo", {"from": head, "to": parent}, parent, None)
        return int(parent)

    def redo(self, author: str, revision: int | None = None) -> int:
        """Return to the revision the last undo left, unless a new revision was made since.

        ``revision`` (the head the caller saw) makes a retry idempotent, as for :meth:`undo`.
        """
        with self._write() as conn:
            self._check_expected(conn)
            head = _head_of(conn)
            if revision is not None and head != revision:
                return self._repeated(conn, "redo", revision, head)
            stack = _redo_stack(_entries(conn))
            if not stack:
                raise self._error("nothing to redo")
            target = stack[-1]
            _insert_entry(conn, author, "redo", {"from": head, "to": target}, target, None)
        return target

    def _repeated(self, conn: sqlite3.Connection, kind: str, revision: int, head: int | None) -> int:
        """The result of an undo/redo of ``revision`` that already happened, else StaleRevisionError."""
        last = conn.execute(
            "SELECT kind, parameters, head FROM entries WHERE head IS NOT NULL ORDER BY id DESC LIMIT 1"
        ).fetchone()
        if last is not None and last[0] == kind and json.loads(last[1]).get("from") == revision:
            return int(last[2])
        raise StaleRevisionError(self.path.parent, revision, head, _since(conn, revision))

    def _check_expected(self, conn: sqlite3.Connection) -> None:
        expected = _expected_head.get()
        if expected is None:
            return
        head = _head_of(conn)
        if head != expected and not (head is None and expected == 0):  # revision 0 is the files' own poses
            raise StaleRevisionError(self.path.parent, expected, head, _since(conn, expected))

    def since(self, revision: int) -> list[JournalEntry]:
        """The entries that changed the head after ``revision`` was last current (who did what since)."""
        with closing(self._connect()) as conn:
            return _since(conn, revision)

    # -------------------------------------------------------------- reading

    @property
    def head(self) -> int | None:
        """The current revision, or None before revision 0 was stored."""
        with closing(self._connect()) as conn:
            return _head_of(conn)

    def head_entry(self) -> JournalEntry | None:
        """The entry that made the current revision current - who moved the head last, how and when
        (what a page is told the moment it happens); None before revision 0 was stored."""
        with closing(self._connect()) as conn:
            row = conn.execute(
                "SELECT id, time, author, kind, parameters, head, revision FROM entries"
                " WHERE head IS NOT NULL ORDER BY id DESC LIMIT 1"
            ).fetchone()
        return None if row is None else JournalEntry(row[0], row[1], row[2], row[3], json.loads(row[4]), row[5], row[6])

    def can_undo(self) -> bool:
        head = self.head
        found = None if head is None else self.revision(head)
        return found is not None and found.parent is not None

    def can_redo(self) -> bool:
        return bool(self.redo_stack())

    def redo_stack(self) -> list[int]:
        with closing(self._connect()) as conn:
            return _redo_stack(_entries(conn))

    def entries(self) -> list[JournalEntry]:
        with closing(self._connect()) as conn:
            return _entries(conn)

    def revisions(self) -> list[int]:
        with closing(self._connect()) as conn:
            return [int(r[0]) for r in conn.execute("SELECT number FROM revisions ORDER BY number")]

    def revision(self, number: int) -> Revision | None:
        with closing(self._connect()) as conn:
            return _find_revision(conn, number)


# ------------------------------------------------------------------ inside one transaction


def _insert_entry(
    conn: sqlite3.Connection, author: str, kind: str, parameters: dict[str, Any], head: int | None, rev: int | None
) -> JournalEntry:
    time = now()
    params = to_jsonable(parameters)
    cur = conn.execute(
        "INSERT INTO entries (time, author, kind, parameters, head, revision) VALUES (?,?,?,?,?,?)",
        (time, author or "anonymous", kind, json.dumps(params), head, rev),
    )
    return JournalEntry(int(cur.lastrowid or 0), time, author or "anonymous", kind, params, head, rev)


def _find_revision(conn: sqlite3.Connection, number: int) -> Revision | None:
    row = conn.execute(
        "SELECT number, parent, entry_id, scans, poses, graph FROM revisions WHERE number=?", (number,)
    ).fetchone()
    if row is None:
        return None
    stack = np.frombuffer(row[4], dtype=np.float64).reshape(int(row[3]), 4, 4)
    return Revision(int(row[0]), row[1], int(row[2]), [m.copy() for m in stack], json.loads(row[5]))


def _revision_of(conn: sqlite3.Connection, number: int) -> Revision:
    found = _find_revision(conn, number)
    if found is None:
        raise LookupError(f"journal names revision {number}, which is not stored")
    return found


def _since(conn: sqlite3.Connection, revision: int) -> list[JournalEntry]:
    entries = [e for e in _entries(conn) if e.head is not None]
    last = max((n for n, e in enumerate(entries) if e.head == revision), default=None)
    return entries if last is None else entries[last + 1 :]


def _first_change_of(conn: sqlite3.Connection, base: int, scans: list[int]) -> JournalEntry | None:
    """The first head change after ``base`` that moved one of ``scans`` (to name who did)."""
    previous = _revision_of(conn, base).poses
    for entry in _since(conn, base):
        poses = _revision_of(conn, int(entry.head or 0)).poses
        if any(not np.array_equal(previous[k], poses[k]) for k in scans):
            return entry
        previous = poses
    return None


def _head_of(conn: sqlite3.Connection) -> int | None:
    row = conn.execute("SELECT head FROM entries WHERE head IS NOT NULL ORDER BY id DESC LIMIT 1").fetchone()
    return None if row is None else int(row[0])


def _entries(conn: sqlite3.Connection) -> list[JournalEntry]:
    rows = conn.execute("SELECT id, time, author, kind, parameters, head, revision FROM entries ORDER BY id")
    return [JournalEntry(r[0], r[1], r[2], r[3], json.loads(r[4]), r[5], r[6]) for r in rows]


def _redo_stack(entries: list[JournalEntry]) -> list[int]:
    """Replay undo/redo entries: an undo pushes the revision it left, a redo pops, a new revision clears."""
    stack: list[int] = []
    for e in entries:
        if e.kind == "undo":
            stack.append(int(e.parameters["from"]))
        elif e.kind == "redo":
            if stack:
                stack.pop()
        elif e.revision is not None:
            stack.clear()
    return stack


# ------------------------------------------------------------------ checking a journal file


def check_journal_file(path: Path) -> list[str]:
    """What is wrong with a journal file: empty when it is sound. Nothing is written to it.

    Checked: SQLite's own ``PRAGMA integrity_check``; the two tables present; no triggers or views
    (the journal has none, and a file from elsewhere must not run code on our inserts); every
    revision's pose blob the size its scan count says, every pose rigid; every entry's parameters
    JSON. Used when a server starts (a session that fails is reported, not opened) and before a
    bundle's journal is taken in.
    """
    if not path.is_file():
        return [f"{path.name}: missing"]
    problems: list[str] = []
    try:
        # Not opened read-only: a journal left by a killed writer has a WAL to recover first.
        with closing(sqlite3.connect(path, timeout=30)) as conn:
            conn.execute("PRAGMA trusted_schema=OFF")
            result = [row[0] for row in conn.execute("PRAGMA integrity_check")]
            if result != ["ok"]:
                return [f"{path.name}: integrity check failed: {'; '.join(map(str, result[:5]))}"]
            objects = {(kind, name) for kind, name in conn.execute("SELECT type, name FROM sqlite_master")}
            for table in ("entries", "revisions"):
                if ("table", table) not in objects:
                    problems.append(f"{path.name}: table '{table}' missing")
            foreign = sorted(name for kind, name in objects if kind in ("trigger", "view"))
            if foreign:
                problems.append(f"{path.name}: holds triggers or views ({', '.join(foreign[:5])}); a journal has none")
            if problems:
                return problems
            for number, scans, blob in conn.execute("SELECT number, scans, poses FROM revisions ORDER BY number"):
                problems.extend(_revision_problems(number, scans, blob))
            for entry_id, parameters in conn.execute("SELECT id, parameters FROM entries ORDER BY id"):
                try:
                    json.loads(parameters)
                except (TypeError, ValueError):
                    problems.append(f"entry {entry_id}: parameters are not JSON")
    except sqlite3.DatabaseError as exc:
        return [f"{path.name}: not a readable SQLite journal ({exc})"]
    return problems


def _revision_problems(number: Any, scans: Any, blob: Any) -> list[str]:
    if not isinstance(number, int) or not isinstance(scans, int) or not isinstance(blob, bytes):
        return [f"revision {number}: malformed row"]
    if scans < 1 or len(blob) != scans * 16 * 8:
        return [f"revision {number}: pose data of {len(blob)} bytes does not hold {scans} poses"]
    stack = np.frombuffer(blob, dtype=np.float64).reshape(scans, 4, 4)
    problems = []
    for index, pose in enumerate(stack):
        try:
            check_rigid(pose, f"revision {number} poses[{index}]")
        except InvalidValueError as exc:
            problems.append(str(exc))
    return problems
