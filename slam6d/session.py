"""A session: a folder that says which scans to map and remembers everything done to them.

Layout::

    SESSION/
      session.toml      name, scan source path(s), format, frame/units, read filters, engine parameters
      journal.sqlite    append-only journal: every run and edit (time, author, kind, parameters),
                        and the pose revisions those produced
      cache/            binary copy of the parsed scans (rebuilt when a source file changes)

Poses are stored per revision in the canonical frame (metres, z up, ``world_from_scan``).
Revision 0 holds the poses the source files carried (odometry). The journal is never rewritten:
undo and redo are entries too, and the current revision ("head") and the redo stack are derived
by replaying the journal, so two processes (or browsers) that append see the same history.

This module is engine-side (the CLI renders sessions too), so it knows nothing of the web.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import sqlite3
import tomllib
from collections.abc import Callable, Iterator, Sequence
from contextlib import closing, contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.errors import FormatError, Slam6dError
from slam6d.geometry import CONVENTIONS, FrameConvention, Matrix
from slam6d.io.registry import ReadOptions, list_scan_files, read_sequence, resolve_format
from slam6d.scan import Scan, ScanSequence

SESSION_FILE = "session.toml"
JOURNAL_FILE = "journal.sqlite"
CACHE_DIR = "cache"
_CACHE_VERSION = 1
_NAME_OK = re.compile(r"^[^\x00-\x1f]{1,200}$")


class SessionError(Slam6dError):
    """A session folder is missing, malformed, or an operation on its journal is impossible."""

    def __init__(self, path: Path | str, message: str) -> None:
        self.path = Path(path)
        self.reason = message
        super().__init__(f"{self.path}: {message}")


@dataclass(frozen=True)
class SessionConfig:
    """The contents of ``session.toml``."""

    name: str
    sources: tuple[str, ...]  # relative to the session folder, or absolute
    format_name: str
    frame: str  # a FrameConvention name (units follow from it)
    min_range: float | None = None  # native units, as ReadOptions
    max_range: float | None = None
    engine: dict[str, Any] = field(default_factory=dict)
    created: str = ""

    @property
    def convention(self) -> FrameConvention:
        return CONVENTIONS[self.frame]


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


# ------------------------------------------------------------------ toml writing (tomllib only reads)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"cannot store {value} in session.toml")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # JSON string escapes are valid TOML basic strings
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise ValueError(f"cannot store {type(value).__name__} in session.toml")


def _dump_toml(data: dict[str, Any]) -> str:
    """Write top-level keys, then one level of tables: all a session file needs."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict) and v is not None]
    for table, values in data.items():
        if isinstance(values, dict):
            lines.append(f"\n[{table}]")
            for k, v in values.items():
                if isinstance(v, dict):
                    raise ValueError(f"nested table [{table}.{k}] is not supported in session.toml")
                if v is not None:
                    lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


# ------------------------------------------------------------------ the session


class Session:
    """One session folder. Cheap to open; scans are loaded only by :meth:`load_sequence`."""

    def __init__(self, folder: Path, config: SessionConfig) -> None:
        self.folder = folder
        self.config = config
        self._init_journal()

    # -------------------------------------------------------------- creation and opening

    @classmethod
    def create(
        cls,
        folder: Path | str,
        name: str,
        source: Path | str | Sequence[Path | str],
        format_name: str | None = None,
        frame: str | None = None,
        min_range: float | None = None,
        max_range: float | None = None,
        engine: dict[str, Any] | None = None,
    ) -> Session:
        """Make a new session folder over existing scans (which stay where they are).

        The source is validated now (format known, scans discoverable) so that a bad folder is
        refused at creation rather than when someone first opens the session.
        """
        folder = Path(folder)
        if (folder / SESSION_FILE).exists():
            raise SessionError(folder, "a session already exists here")
        if not name or not _NAME_OK.match(name):
            raise SessionError(folder, "a session needs a name of 1-200 printable characters")
        sources = [Path(source)] if isinstance(source, str | Path) else [Path(s) for s in source]
        if not sources:
            raise SessionError(folder, "a session needs at least one scan source")
        fmt = None
        for src in sources:
            resolved = src if src.is_absolute() else folder / src
            if not resolved.exists():
                raise SessionError(folder, f"scan source {src} does not exist")
            fmt = resolve_format(resolved, format_name)
            if resolved.is_dir():
                list_scan_files(resolved, fmt)
        assert fmt is not None
        frame = frame or fmt.convention.name
        if frame not in CONVENTIONS:
            raise SessionError(folder, f"unknown frame '{frame}'; known: {', '.join(sorted(CONVENTIONS))}")
        config = SessionConfig(
            name=name,
            sources=tuple(str(s) for s in sources),
            format_name=fmt.name,
            frame=frame,
            min_range=min_range,
            max_range=max_range,
            engine=dict(engine or {}),
            created=_now(),
        )
        folder.mkdir(parents=True, exist_ok=True)
        write_config(folder, config)
        return cls(folder, config)

    @classmethod
    def open(cls, folder: Path | str) -> Session:
        folder = Path(folder)
        return cls(folder, read_config(folder))

    @property
    def id(self) -> str:
        return self.folder.name

    @property
    def name(self) -> str:
        return self.config.name

    def source_paths(self) -> list[Path]:
        return [p if p.is_absolute() else self.folder / p for p in map(Path, self.config.sources)]

    def scan_files(self) -> list[Path]:
        """The scan files in acquisition order, without reading them (for listings)."""
        files: list[Path] = []
        for src in self.source_paths():
            fmt = resolve_format(src, self.config.format_name)
            files.extend(list_scan_files(src, fmt) if src.is_dir() else [src])
        return files

    def update_engine(self, parameters: dict[str, Any], author: str) -> None:
        """Change engine parameters (kept in session.toml, and journaled so the change has an author)."""
        engine = {**self.config.engine, **parameters}
        self.config = SessionConfig(**{**self.config.__dict__, "engine": engine})
        write_config(self.folder, self.config)
        self.append(author, "parameters", parameters)

    # -------------------------------------------------------------- scans

    def load_sequence(self, progress: Callable[[int, int], None] | None = None) -> ScanSequence:
        """Read the scans (from the cache when the sources are unchanged) with the current poses.

        Creates revision 0 from the poses the source carried the first time it is called.
        """
        sequence = self._read_cached(progress)
        if self._head() is None:
            self.commit(sequence.poses(), "system", "import", {"scans": len(sequence)})
        poses = self.poses()
        if len(poses) != len(sequence):
            raise SessionError(
                self.folder, f"journal has poses for {len(poses)} scans but the source now has {len(sequence)}"
            )
        for scan, pose in zip(sequence.scans, poses, strict=True):
            scan.pose = pose
        return sequence

    def _read_options(self) -> ReadOptions:
        return ReadOptions(self.config.min_range, self.config.max_range)

    def _fingerprint(self) -> str:
        digest = hashlib.sha256(f"v{_CACHE_VERSION}|{self.config.format_name}|{self.config.frame}".encode())
        digest.update(f"|{self.config.min_range}|{self.config.max_range}".encode())
        for src in self.source_paths():
            entries = sorted(src.iterdir()) if src.is_dir() else [src]
            for p in entries:
                if p.is_file():
                    st = p.stat()
                    digest.update(f"|{p}|{st.st_size}|{st.st_mtime_ns}".encode())
        return digest.hexdigest()

    def _read_cached(self, progress: Callable[[int, int], None] | None) -> ScanSequence:
        cache = self.folder / CACHE_DIR / "scans.npz"
        fingerprint = self._fingerprint()
        if cache.exists():
            try:
                with np.load(cache, allow_pickle=False) as data:
                    if str(data["fingerprint"]) == fingerprint:
                        return _sequence_from_arrays(data, self.config)
            except (OSError, ValueError, KeyError):
                pass  # a damaged cache is simply rebuilt
        sequences = [
            read_sequence(
                src, self.config.format_name, self._read_options(), convention=self.config.convention, progress=progress
            )
            for src in self.source_paths()
        ]
        scans = [scan for seq in sequences for scan in seq.scans]
        sequence = ScanSequence(scans, self.config.convention, self.source_paths()[0], self.config.format_name)
        cache.parent.mkdir(exist_ok=True)
        tmp = cache.with_suffix(".tmp.npz")
        np.savez(tmp, fingerprint=np.array(fingerprint), **_sequence_to_arrays(sequence))  # type: ignore[arg-type]
        tmp.replace(cache)
        return sequence

    # -------------------------------------------------------------- journal

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.folder / JOURNAL_FILE, timeout=30, isolation_level=None)
        conn.execute("PRAGMA journal_mode=WAL")
        return conn

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction; BEGIN IMMEDIATE so two writers cannot both read the same head."""
        with closing(self._connect()) as conn:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def _init_journal(self) -> None:
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

    def append(
        self, author: str, kind: str, parameters: dict[str, Any] | None = None, conn: sqlite3.Connection | None = None
    ) -> JournalEntry:
        """Record something that does not change poses (a rejected loop, a setting, a failed run)."""
        if conn is None:
            with self._write() as c:
                return self.append(author, kind, parameters, c)
        head = _head_of(conn)
        return _insert_entry(conn, author, kind, parameters or {}, head, None)

    def commit(
        self,
        poses: Sequence[Matrix],
        author: str,
        kind: str,
        parameters: dict[str, Any] | None = None,
        graph: dict[str, Any] | None = None,
    ) -> int:
        """Store a new pose revision as a child of the current one and make it current."""
        stack = np.stack([np.asarray(p, dtype=np.float64).reshape(4, 4) for p in poses])
        if not np.isfinite(stack).all():
            raise SessionError(self.folder, f"refusing to store non-finite poses ({kind})")
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
                raise SessionError(self.folder, "nothing to undo")
            _insert_entry(conn, author, "undo", {"from": head, "to": parent}, parent, None)
        return parent

    def redo(self, author: str) -> int:
        with self._write() as conn:
            stack = _redo_stack(_entries(conn))
            if not stack:
                raise SessionError(self.folder, "nothing to redo")
            target = stack[-1]
            _insert_entry(conn, author, "redo", {"from": _head_of(conn), "to": target}, target, None)
        return target

    def _head(self) -> int | None:
        with closing(self._connect()) as conn:
            return _head_of(conn)

    @property
    def revision(self) -> int:
        """The current revision number (0 before anything was loaded or edited)."""
        head = self._head()
        return 0 if head is None else head

    def can_undo(self) -> bool:
        rev = self._revision_row(self._head()) if self._head() is not None else None
        return rev is not None and rev.parent is not None

    def can_redo(self) -> bool:
        return bool(self.redo_stack())

    def redo_stack(self) -> list[int]:
        with closing(self._connect()) as conn:
            return _redo_stack(_entries(conn))

    def journal(self) -> list[JournalEntry]:
        with closing(self._connect()) as conn:
            return _entries(conn)

    def revisions(self) -> list[int]:
        with closing(self._connect()) as conn:
            return [int(r[0]) for r in conn.execute("SELECT number FROM revisions ORDER BY number")]

    def _revision_row(self, number: int | None) -> Revision | None:
        if number is None:
            return None
        with closing(self._connect()) as conn:
            row = conn.execute(
                "SELECT number, parent, entry_id, scans, poses, graph FROM revisions WHERE number=?", (number,)
            ).fetchone()
        if row is None:
            return None
        stack = np.frombuffer(row[4], dtype=np.float64).reshape(int(row[3]), 4, 4)
        return Revision(int(row[0]), row[1], int(row[2]), [m.copy() for m in stack], json.loads(row[5]))

    def get_revision(self, rev: int | None = None) -> Revision:
        number = self._head() if rev is None else rev
        if number is None:
            self.load_sequence()  # materialises revision 0 from the source
            number = self._head()
        found = self._revision_row(number)
        if found is None:
            raise SessionError(self.folder, f"no revision {rev}; revisions are 0..{max(self.revisions(), default=0)}")
        return found

    def poses(self, rev: int | None = None) -> list[Matrix]:
        """Canonical ``world_from_scan`` per scan at ``rev`` (default: the current revision)."""
        return self.get_revision(rev).poses

    def graph(self, rev: int | None = None) -> dict[str, Any]:
        """The pose-graph annotations (loops accepted, edges added or removed by hand) at ``rev``."""
        return self.get_revision(rev).graph

    # -------------------------------------------------------------- render keyframes

    def camera_path(self) -> list[dict[str, Any]]:
        """Render keyframes, as last saved: dicts as in a camera-path file (position, orientation_wxyz, fov_deg)."""
        for entry in reversed(self.journal()):
            if entry.kind == "camera_path":
                return list(entry.parameters.get("keyframes", []))
        return []

    def set_camera_path(self, keyframes: list[dict[str, Any]], author: str) -> None:
        self.append(author, "camera_path", {"keyframes": keyframes})


# ------------------------------------------------------------------ helpers (module level: used in transactions)


def _insert_entry(
    conn: sqlite3.Connection, author: str, kind: str, parameters: dict[str, Any], head: int | None, rev: int | None
) -> JournalEntry:
    from slam6d.trace import to_jsonable

    time = _now()
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


def read_config(folder: Path) -> SessionConfig:
    path = folder / SESSION_FILE
    if not path.is_file():
        raise SessionError(folder, f"not a session folder (no {SESSION_FILE})")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(path, f"invalid TOML: {exc}") from None
    source = data.get("source", {})
    name = data.get("name")
    paths = source.get("paths")
    if not isinstance(name, str) or not name:
        raise FormatError(path, "missing 'name'")
    if not isinstance(paths, list) or not paths or not all(isinstance(p, str) for p in paths):
        raise FormatError(path, "[source] needs 'paths', a list of scan folders or files")
    format_name = source.get("format")
    if not isinstance(format_name, str):
        raise FormatError(path, "[source] needs 'format' (see `slam6d formats`)")
    frame = source.get("frame", "canonical")
    if frame not in CONVENTIONS:
        raise FormatError(path, f"[source] frame '{frame}' unknown; known: {', '.join(sorted(CONVENTIONS))}")
    return SessionConfig(
        name=name,
        sources=tuple(paths),
        format_name=format_name,
        frame=frame,
        min_range=source.get("min_range"),
        max_range=source.get("max_range"),
        engine=dict(data.get("engine", {})),
        created=str(data.get("created", "")),
    )


def write_config(folder: Path, config: SessionConfig) -> None:
    conv = config.convention
    data: dict[str, Any] = {
        "name": config.name,
        "created": config.created or None,
        "source": {
            "paths": list(config.sources),
            "format": config.format_name,
            "frame": config.frame,
            "metres_per_unit": conv.metres_per_unit,  # informative: the frame fixes it
            "min_range": config.min_range,
            "max_range": config.max_range,
        },
        "engine": dict(config.engine),
    }
    path = folder / SESSION_FILE
    tmp = path.with_suffix(".toml.tmp")
    tmp.write_text(_dump_toml(data))
    tmp.replace(path)


def _sequence_to_arrays(sequence: ScanSequence) -> dict[str, np.ndarray]:
    counts = np.array([len(s) for s in sequence.scans], dtype=np.int64)
    # float32 is ample in each scanner's own frame (sub-micrometre at 100 m) and halves the cache.
    points = np.concatenate([s.points for s in sequence.scans]).astype(np.float32)
    has_intensity = all(s.intensity is not None for s in sequence.scans)
    arrays: dict[str, np.ndarray] = {
        "counts": counts,
        "points": points,
        "poses": np.stack([s.pose for s in sequence.scans]),
        "has_pose": np.array([s.has_pose for s in sequence.scans]),
        "names": np.array([s.name for s in sequence.scans]),
        "files": np.array([str(s.source or "") for s in sequence.scans]),
    }
    if has_intensity:
        arrays["intensity"] = np.concatenate([s.intensity for s in sequence.scans if s.intensity is not None])
    return arrays


def _sequence_from_arrays(data: Any, config: SessionConfig) -> ScanSequence:
    counts = data["counts"]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    points = data["points"]
    intensity = data["intensity"] if "intensity" in data.files else None
    scans = []
    for k in range(len(counts)):
        a, b = int(offsets[k]), int(offsets[k + 1])
        scans.append(
            Scan(
                points[a:b].astype(np.float64),
                data["poses"][k].copy(),
                name=str(data["names"][k]),
                source=Path(str(data["files"][k])) if str(data["files"][k]) else None,
                intensity=None if intensity is None else intensity[a:b].copy(),
                has_pose=bool(data["has_pose"][k]),
            )
        )
    return ScanSequence(scans, config.convention, None, config.format_name)


def list_sessions(root: Path | str) -> list[Session]:
    """The sessions directly inside ``root`` (folders with a session.toml), by folder name."""
    root = Path(root)
    if not root.is_dir():
        return []
    return [Session.open(p) for p in sorted(root.iterdir()) if (p / SESSION_FILE).is_file()]
