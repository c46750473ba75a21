"""A session: a folder that says which scans to map and remembers everything done to them.

Layout::

    SESSION/
      session.toml      name, scan source path(s), format, frame/units, read filters, engine parameters
      journal.sqlite    append-only journal: every run and edit (time, author, kind, parameters),
                        and the pose revisions those produced
      cache/            binary copy of the parsed scans (rebuilt when a source file changes)

Poses are stored per revision in the canonical frame (metres, z up, ``world_from_scan``), in the
journal (:mod:`slam6d.journal`); revision 0 holds the poses the source files carried (odometry).
The cache is :mod:`slam6d.scan_cache`.

This module is engine-side (the CLI renders sessions too), so it knows nothing of the web.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slam6d.attitude import declared_tilt_noise
from slam6d.camera_path import Keyframe, keyframe_from_dict, keyframe_to_dict
from slam6d.errors import FormatError, InvalidValueError, SessionError
from slam6d.geometry import CONVENTIONS, FrameConvention, Matrix
from slam6d.io.registry import ReadOptions, list_scan_files, resolve_format
from slam6d.io.source import check_regular_file
from slam6d.journal import Journal, Revision, now
from slam6d.scan import ScanSequence
from slam6d.scan_cache import ScanCache

SESSION_FILE = "session.toml"
JOURNAL_FILE = "journal.sqlite"
CACHE_DIR = "cache"
_NAME_OK = re.compile(r"^[^\x00-\x1f]{1,200}$")


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


# ------------------------------------------------------------------ the session


class Session:
    """One session folder. Cheap to open; scans are loaded only by :meth:`load_sequence`."""

    def __init__(self, folder: Path, config: SessionConfig) -> None:
        self.folder = folder
        self.config = config
        self.journal = Journal(folder / JOURNAL_FILE)

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
        refused at creation rather than when someone first opens the session. A source that
        declares an inclinometer (:func:`slam6d.attitude.declared_tilt_noise`: a simulated
        session) puts its noise into ``[engine] tilt_noise_deg`` unless ``engine`` sets it, so the
        workbench's runs hold the scans' tilt as ``slam6d run`` does on the same folder.
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
            if not resolved.is_dir():
                check_regular_file(resolved)  # a device or FIFO named as a scan is refused now, unread
            fmt = resolve_format(resolved, format_name)
            if resolved.is_dir():
                list_scan_files(resolved, fmt)
        assert fmt is not None
        engine = dict(engine or {})
        if "tilt_noise_deg" not in engine:  # the source's inclinometer, written down where it can be seen and changed
            declared = [declared_tilt_noise(s if s.is_absolute() else folder / s) for s in sources]
            if len(set(declared)) == 1 and declared[0] is not None:
                engine["tilt_noise_deg"] = declared[0]
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
            engine=engine,
            created=now(),
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
        self.journal.append(author, "parameters", parameters)

    # -------------------------------------------------------------- scans

    def scan_cache(self) -> ScanCache:
        """The binary copy of the parsed scans; its fingerprint names the sources as they are now read."""
        options = ReadOptions(self.config.min_range, self.config.max_range)
        return ScanCache(
            self.folder / CACHE_DIR / "scans.npz",
            self.source_paths(),
            self.config.format_name,
            self.config.convention,
            options,
        )

    def load_sequence(self, progress: Callable[[int, int], None] | None = None) -> ScanSequence:
        """Read the scans (from the cache when the sources are unchanged) with the current poses.

        Creates revision 0 from the poses the source carried the first time it is called.
        """
        sequence = self.scan_cache().load(progress)
        if self.journal.head is None:
            self.journal.commit_first(sequence.poses(), "system", "import", {"scans": len(sequence)})
        poses = self.poses()
        if len(poses) != len(sequence):
            raise SessionError(
                self.folder, f"journal has poses for {len(poses)} scans but the source now has {len(sequence)}"
            )
        for scan, pose in zip(sequence.scans, poses, strict=True):
            scan.pose = pose
        return sequence

    # -------------------------------------------------------------- revisions

    @property
    def revision(self) -> int:
        """The current revision number (0 before anything was loaded or edited)."""
        head = self.journal.head
        return 0 if head is None else head

    def get_revision(self, rev: int | None = None) -> Revision:
        number = self.journal.head if rev is None else rev
        if number is None:
            self.load_sequence()  # materialises revision 0 from the source
            number = self.journal.head
        found = None if number is None else self.journal.revision(number)
        if found is None:
            last = max(self.journal.revisions(), default=0)
            raise SessionError(self.folder, f"no revision {rev}; revisions are 0..{last}")
        return found

    def poses(self, rev: int | None = None) -> list[Matrix]:
        """Canonical ``world_from_scan`` per scan at ``rev`` (default: the current revision)."""
        return self.get_revision(rev).poses

    def graph(self, rev: int | None = None) -> dict[str, Any]:
        """The pose-graph annotations (loops accepted, edges added or removed by hand) at ``rev``."""
        return self.get_revision(rev).graph

    # -------------------------------------------------------------- render keyframes

    def camera_path(self) -> list[dict[str, Any]]:
        """Render keyframes, as last saved: dicts as in a camera-path file (position, orientation_wxyz, fov_deg).

        Keyframes that cannot be rendered (stored by an older version that did not check them) are
        left out, so a poisoned entry never wedges the path: :meth:`camera_path_problems` names them.
        """
        return self._saved_camera_path()[0]

    def camera_path_problems(self) -> list[str]:
        """Why each keyframe of the last saved path that :meth:`camera_path` leaves out is unusable."""
        return self._saved_camera_path()[1]

    def _saved_camera_path(self) -> tuple[list[dict[str, Any]], list[str]]:
        latest = self.journal.latest("camera_path")
        return ([], []) if latest is None else _usable_keyframes(latest.parameters)

    def set_camera_path(self, keyframes: Sequence[dict[str, Any] | Keyframe], author: str) -> list[dict[str, Any]]:
        """Replace the render keyframes (an empty list clears them); returns them as stored, normalised."""
        return self.change_camera_path(lambda _old: list(keyframes), author)

    def change_camera_path(
        self, change: Callable[[list[dict[str, Any]]], Sequence[dict[str, Any] | Keyframe]], author: str
    ) -> list[dict[str, Any]]:
        """Apply ``change`` to the keyframes as stored at the moment of writing (two keyframes added at
        once are both kept); returns the new keyframes.

        Every keyframe of the result is checked first (finite, bounded position; non-zero quaternion,
        normalised; field of view in range): one bad keyframe refuses the whole change, and an
        exception from ``change`` stores nothing either.
        """

        def checked(doc: dict[str, Any] | None) -> dict[str, Any]:
            current = [] if doc is None else _usable_keyframes(doc)[0]
            return {
                "keyframes": [
                    keyframe_to_dict(k if isinstance(k, Keyframe) else keyframe_from_dict(k, f"keyframes[{i}]"))
                    for i, k in enumerate(change(current))
                ]
            }

        entry = self.journal.update_document(author, "camera_path", checked)
        return list(entry.parameters["keyframes"])


def _usable_keyframes(document: dict[str, Any]) -> tuple[list[dict[str, Any]], list[str]]:
    """The keyframes of a stored camera-path document that can be rendered, and why the others cannot."""
    raw = document.get("keyframes", [])
    items = raw if isinstance(raw, list) else []
    kept: list[dict[str, Any]] = []
    problems: list[str] = [] if isinstance(raw, list) else ["keyframes: not a list"]
    for i, item in enumerate(items):
        try:
            kept.append(keyframe_to_dict(keyframe_from_dict(item, f"keyframes[{i}]")))
        except InvalidValueError as exc:
            problems.append(str(exc))
    return kept, problems


# ------------------------------------------------------------------ session.toml


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


def slugify(name: str) -> str:
    """A folder name for a session called ``name``: letters, digits, '.', '_', '-' only."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-._")[:60]
    return slug or "session"


def reserve_session_folder(root: Path, name: str) -> Path:
    """Create (empty) and return a new folder for a session called ``name`` inside ``root``.

    ``name``, then ``name-2``, ``name-3``...: the folder is made with an exclusive ``mkdir``, so two
    sessions created at once never share one.
    """
    base, n = slugify(name), 1
    root.mkdir(parents=True, exist_ok=True)
    while True:
        candidate = root / (base if n == 1 else f"{base}-{n}")
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            n += 1


def list_sessions(root: Path | str) -> list[Session]:
    """The sessions directly inside ``root`` (folders with a session.toml), by folder name."""
    root = Path(root)
    if not root.is_dir():
        return []
    return [Session.open(p) for p in sorted(root.iterdir()) if (p / SESSION_FILE).is_file()]
