"""A session's history: an append-only SQLite journal of everything done, and the pose revisions.

Every run and edit is an entry (time, author, kind, parameters). An entry that changes poses also
stores a revision: all poses (canonical ``world_from_scan``) and the pose-graph annotations, as a
child of the revision current when it was made. The journal is never rewritten: undo and redo are
entries too, and the current revision ("head") and the redo stack are derived by replaying it, so
two processes (or browsers) that append see the same history. Each write is one ``BEGIN
IMMEDIATE`` transaction, so two writers cannot both build on the same head.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterator, Sequence
from contextlib import closing, contextmanager
from dataclasses import dataclass
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
            return _insert_entry(conn, author, kind, parameters or {}, _head_of(conn), None)

    def commit(
        self,
        poses: Sequence[Matrix],
        author: str,
        kind: str,
        parameters: dict[str, Any] | None = None,
        graph: dict[str, Any] | None = None,
    ) -> int:
        """Store a new pose revision as a child of the current one and make it current.

        Without ``graph`` the new revision keeps its parent's annotations. Every pose must be rigid
        (:func:`slam6d.geometry.check_rigid`): a revision is kept forever, so a pose that is not one
        is refused here with an :class:`InvalidValueError` naming it, and nothing is written.
        """
        if not poses:
            raise self._error(f"refusing to store a revision without poses ({kind})")
        stack = np.stack([check_rigid(p, f"poses[{i}]") for i, p in enumerate(poses)])
        with self._write() as conn:
            parent = _head_of(conn)
            number = int(conn.execute("SELECT COALESCE(MAX(number), -1) + 1 FROM revisions").fetchone()[0])
            if graph is None and parent is not None:
                graph = json.loads(conn.execute("SELECT graph FROM revisions WHERE number=?", (parent,)).fetchone()[0])
            entry = _insert_entry(conn, author, kind, parameters or {}, number, number)
            conn.execute(
                "INSERT INTO revisions (number, parent, entry_id, scans, poses, graph) VALUES (?,?,?,?,?,?)",
                (number, parent, entry.id, len(stack), stack.tobytes(), json.dumps(graph or {})),
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
        stack = np.stack([check_rigid(p, f"poses[{i}]") for i, p in enumerate(poses)])
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

    def undo(self, author: str) -> int:
        """Go back to the parent of the current revision (an entry of its own; nothing is deleted)."""
        with self._write() as conn:
            head = _head_of(conn)
            parent = (
                None
                if head is None
                else conn.execute("SELECT parent FROM revisions WHERE number=?", (head,)).fetchone()[0]
            )
            if parent is None:
                raise self._error("nothing to undo")
            _insert_entry(conn, author, "undo", {"from": head, "to": parent}, parent, None)
        return int(parent)

    def redo(self, author: str) -> int:
        """Return to the revision the last undo left, unless a new revision was made since."""
        with self._write() as conn:
            stack = _redo_stack(_entries(conn))
            if not stack:
                raise self._error("nothing to redo")
            target = stack[-1]
            _insert_entry(conn, author, "redo", {"from": _head_of(conn), "to": target}, target, None)
        return target

    # -------------------------------------------------------------- reading

    @property
    def head(self) -> int | None:
        """The current revision, or None before revision 0 was stored."""
        with closing(self._connect()) as conn:
            return _head_of(conn)

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
            row = conn.execute(
                "SELECT number, parent, entry_id, scans, poses, graph FROM revisions WHERE number=?", (number,)
            ).fetchone()
        if row is None:
            return None
        stack = np.frombuffer(row[4], dtype=np.float64).reshape(int(row[3]), 4, 4)
        return Revision(int(row[0]), row[1], int(row[2]), [m.copy() for m in stack], json.loads(row[5]))


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
