"""Session bundles: one zip that hands a whole session - its history, not just its poses - to someone else.

A bundle holds ``manifest.json`` (format, schema version, the sha256 and size of every other file),
``session.toml``, ``journal.sqlite`` (every entry and revision: edits, runs, undo/redo, camera
paths, comments), ``camera_path.json`` (the current fly-through path, readable by ``slam6d render
--path``), the session's traces and other files, and optionally the scans themselves under
``sources/<k>/``. Without the scans, the manifest records where each scan source was (its absolute
path and, when the exporter names its data root, the path inside it) with the sha256 and size of
every file in it: an importer finds the same files under its own data root (or, on the command
line, where they were) and re-links the session to them after checking every hash, so a bundle of
a large survey can be handed between machines that hold the same scans without copying them.

Importing trusts nothing in the zip: it is unpacked by :mod:`slam6d.archive` (sizes, ratio, entry
count, names, links and nested archives checked while streaming), then every file is checked
against the manifest (no file missing, none extra, every hash equal), ``session.toml`` parsed,
every scan source either inside the bundle or found outside it with every file's hash equal to
the recorded one (:func:`locate_sources`), and the journal
checked (:func:`slam6d.journal.check_journal_file`) - all in a staging folder; only a bundle that
passed becomes a session folder, under a new name, so an import never overwrites anything.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import tempfile
import zipfile
from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

from slam6d.archive import ArchiveError, ArchiveLimits, extract_zip, safe_member_name
from slam6d.camera_path import CameraPath, keyframe_from_dict
from slam6d.journal import check_journal_file, now
from slam6d.session import (
    CACHE_DIR,
    JOURNAL_FILE,
    SESSION_FILE,
    Session,
    read_config,
    reserve_session_folder,
    write_config,
)
from slam6d.trace import write_trace

BUNDLE_FORMAT = "slam6d-session-bundle"
BUNDLE_VERSION = 1
MANIFEST = "manifest.json"
CAMERA_PATH_FILE = "camera_path.json"
SOURCES_DIR = "sources"
# Session-folder parts a bundle never carries: rebuilt caches, rendered videos, files being written.
_LEFT_OUT_DIRS = frozenset({CACHE_DIR, "renders"})
_MANIFEST_MAX_BYTES = 16 << 20


class BundleError(ArchiveError):
    """A bundle was refused (or cannot be written); the message says which file and why."""


@dataclass(frozen=True)
class BundleSummary:
    path: Path
    files: int
    bytes: int
    scans_included: bool


# ------------------------------------------------------------------ export


def export_bundle(
    session: Session | Path | str, out: Path | str, include_scans: bool = False, data_root: Path | None = None
) -> BundleSummary:
    """Write the session's bundle to ``out`` (atomically: a half-written zip never appears there).

    Without the scans, the manifest's ``sources`` record each scan source's files (sha256, size) and
    its path - also relative to ``data_root`` when it lies inside, which is how a server with the
    same data under another folder finds it.
    """
    session = session if isinstance(session, Session) else Session.open(Path(session))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".bundle-", dir=out.parent) as scratch:
        staged = _stage_generated_files(session, Path(scratch), include_scans)
        files = staged + _session_files(session) + (_source_files(session) if include_scans else [])
        partial = Path(scratch) / "bundle.zip"
        manifest: list[dict[str, Any]] = []
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for name, path in files:
                manifest.append({"path": name, "sha256": _sha256(path), "bytes": path.stat().st_size})
                zf.write(path, name)
            head = session.journal.head
            zf.writestr(
                MANIFEST,
                json.dumps(
                    {
                        "format": BUNDLE_FORMAT,
                        "version": BUNDLE_VERSION,
                        "session": session.id,
                        "name": session.name,
                        "exported": now(),
                        "revision": head,
                        "scans_included": include_scans,
                        "files": manifest,
                        **({} if include_scans else {"sources": _source_records(session, data_root)}),
                    },
                    indent=1,
                ),
            )
        os.replace(partial, out)
    return BundleSummary(out, len(manifest), out.stat().st_size, include_scans)


def _stage_generated_files(session: Session, scratch: Path, include_scans: bool) -> list[tuple[str, Path]]:
    """session.toml (sources pointing into the bundle, or absolute), a consistent journal copy, the path."""
    sources = [
        f"{SOURCES_DIR}/{k}" + ("" if path.is_dir() else f"/{path.name}") if include_scans else str(path.resolve())
        for k, path in enumerate(session.source_paths())
    ]
    config_dir = scratch / "config"
    config_dir.mkdir()
    write_config(config_dir, replace(session.config, sources=tuple(sources)))
    journal_copy = scratch / JOURNAL_FILE
    # The backup API copies a consistent snapshot even while a server appends (WAL); the copy is made
    # self-contained (no -wal file) so the zip carries the whole history.
    with (
        closing(sqlite3.connect(session.journal.path, timeout=30)) as source,
        closing(sqlite3.connect(journal_copy)) as copy,
    ):
        source.backup(copy)
        copy.execute("PRAGMA journal_mode=DELETE")
    staged = [(SESSION_FILE, config_dir / SESSION_FILE), (JOURNAL_FILE, journal_copy)]
    keyframes = session.camera_path()
    if keyframes:
        path_file = scratch / CAMERA_PATH_FILE
        write_trace(path_file, CameraPath([keyframe_from_dict(k) for k in keyframes]).to_dict())
        staged.append((CAMERA_PATH_FILE, path_file))
    return staged


def _regular_files(root: Path) -> list[Path]:
    """Regular files under ``root``, sorted, never following a link (a link could lead anywhere)."""
    found = []
    for folder, dirs, names in os.walk(root, followlinks=False):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(names):
            path = Path(folder) / name
            if not name.startswith(".") and not name.endswith(".tmp") and path.is_file() and not path.is_symlink():
                found.append(path)
    return found


def _session_files(session: Session) -> list[tuple[str, Path]]:
    """The session folder's own files (traces, comments...) other than those staged, caches and scans."""
    folder = session.folder.resolve()
    sources = [p.resolve() for p in session.source_paths()]
    out = []
    for path in _regular_files(folder):
        relative = path.relative_to(folder)
        if relative.parts[0] in _LEFT_OUT_DIRS or relative.name.startswith(JOURNAL_FILE):
            continue
        if relative.as_posix() in (SESSION_FILE, MANIFEST, CAMERA_PATH_FILE):
            continue
        if any(path == s or s in path.parents for s in sources):
            continue
        out.append((relative.as_posix(), path))
    return out


def _files_of_source(source: Path) -> list[tuple[str, Path]]:
    """A scan source's files by their path relative to the source (a single file: its name)."""
    if source.is_dir():
        return [(p.relative_to(source).as_posix(), p) for p in _regular_files(source)]
    if source.is_file() and not source.is_symlink():
        return [(source.name, source)]
    raise BundleError(source, "scan source is not a regular file or folder; cannot bundle it")


def _source_files(session: Session) -> list[tuple[str, Path]]:
    return [
        (f"{SOURCES_DIR}/{k}/{name}", path)
        for k, source in enumerate(session.source_paths())
        for name, path in _files_of_source(source)
    ]


def _source_records(session: Session, data_root: Path | None) -> list[dict[str, Any]]:
    """Where each scan source was and what it held: what an importer needs to find the same files."""
    root = None if data_root is None else data_root.expanduser().resolve()
    records = []
    for source in session.source_paths():
        resolved = source.resolve()
        inside = root is not None and resolved.is_relative_to(root)
        records.append(
            {
                "path": str(resolved),
                "data_root_path": resolved.relative_to(root).as_posix() if inside and root is not None else None,
                "kind": "folder" if source.is_dir() else "file",
                "files": [
                    {"path": name, "sha256": _sha256(path), "bytes": path.stat().st_size}
                    for name, path in _files_of_source(source)
                ],
            }
        )
    return records


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        while chunk := stream.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


# ------------------------------------------------------------------ import


def import_bundle(
    archive: Path | BinaryIO,
    sessions_dir: Path | str,
    limits: ArchiveLimits = ArchiveLimits(),
    find_source: SourceFinder | None = None,
    author: str = "system",
    label: str | None = None,
) -> Session:
    """Make a new session in ``sessions_dir`` from a bundle; nothing is written unless it all checks out.

    A bundle without its scans names folders outside itself: ``find_source(recorded)`` says where a
    recorded source path (inside the exporter's data root, or absolute) may be looked for here, or
    None where this importer must not look; without it such a bundle is refused, which is what a
    server that must not open arbitrary folders wants. A source is re-linked only where every file
    the manifest records is present with its sha256 (:func:`locate_sources`). The import is journaled.
    """
    sessions_dir = Path(sessions_dir)
    where = label or (str(archive) if isinstance(archive, Path) else "bundle")
    sessions_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".import-", dir=sessions_dir))
    folder: Path | None = None
    try:
        content = staging / "content"
        written = extract_zip(archive, content, limits, label=where)
        manifest = _check_manifest(content, written, where)
        config = read_config(content)
        located: set[str] = set()
        if manifest.get("scans_included", True) is False:
            found = locate_sources(manifest.get("sources"), len(config.sources), find_source, where)
            located = {str(path) for path in found}
            config = replace(config, sources=tuple(str(path) for path in found))
            write_config(content, config)
        for source in config.sources:
            _check_source(content, source, located, where)
        problems = check_journal_file(content / JOURNAL_FILE)
        if problems:
            raise BundleError(where, f"{JOURNAL_FILE} is unusable: {'; '.join(problems[:3])}")
        (content / MANIFEST).unlink()
        folder = reserve_session_folder(sessions_dir, config.name)
        os.replace(content, folder)  # onto the empty folder just reserved
        session = Session.open(folder)
        session.journal.append(
            author,
            "bundle_import",
            {"from_session": manifest.get("session"), "exported": manifest.get("exported"), "bundle": where},
        )
        return session
    except BaseException:
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _check_manifest(content: Path, written: list[PurePosixPath], where: str) -> dict[str, Any]:
    """The manifest, after proving it lists exactly the files unpacked, each with its hash and size."""
    path = content / MANIFEST
    if not path.is_file():
        raise BundleError(where, f"not a session bundle: no {MANIFEST}")
    if path.stat().st_size > _MANIFEST_MAX_BYTES:
        raise BundleError(where, f"{MANIFEST} is larger than {_MANIFEST_MAX_BYTES // 2**20} MiB")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise BundleError(where, f"{MANIFEST} is not valid JSON") from None
    if not isinstance(manifest, dict) or manifest.get("format") != BUNDLE_FORMAT:
        raise BundleError(where, f"not a session bundle ({MANIFEST} does not say format '{BUNDLE_FORMAT}')")
    version = manifest.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= BUNDLE_VERSION:
        raise BundleError(where, f"bundle version {version!r} is not one this program reads (1..{BUNDLE_VERSION})")
    files = manifest.get("files")
    if not isinstance(files, list):
        raise BundleError(where, f"{MANIFEST}: 'files' must be a list")
    listed: dict[str, dict[str, Any]] = {}
    for i, item in enumerate(files):
        name = item.get("path") if isinstance(item, dict) else None
        if not isinstance(name, str) or safe_member_name(name) is None or name == MANIFEST:
            raise BundleError(where, f"{MANIFEST}: files[{i}] has no usable path")
        if not isinstance(item.get("sha256"), str) or not isinstance(item.get("bytes"), int):
            raise BundleError(where, f"{MANIFEST}: files[{i}] ('{name}') needs sha256 and bytes")
        listed[name] = item
    present = {p.as_posix() for p in written} - {MANIFEST}
    for name in sorted(present - set(listed)):
        raise BundleError(where, f"'{name}' is in the zip but not in {MANIFEST}")
    for name in sorted(set(listed) - present):
        raise BundleError(where, f"'{name}' is listed in {MANIFEST} but missing from the zip")
    for required in (SESSION_FILE, JOURNAL_FILE):
        if required not in listed:
            raise BundleError(where, f"bundle has no {required}")
    for name, item in sorted(listed.items()):
        file = content / name
        if file.stat().st_size != item["bytes"] or _sha256(file) != item["sha256"].lower():
            raise BundleError(where, f"'{name}' does not match its sha256 in {MANIFEST} (damaged or altered)")
    return manifest


def _check_source(content: Path, source: str, located: set[str], where: str) -> None:
    """A scan source must be one of the bundle's own folders, or one :func:`locate_sources` found
    outside it and checked file by file (a path the bundle merely names is never opened)."""
    if source in located:
        return
    inside = safe_member_name(source)
    if inside is None or not (content / inside).exists():
        raise BundleError(where, f"scan source '{source}' is not in the bundle")


SourceFinder = Callable[[str], Path | None]
"""Where a recorded scan source may be looked for on this machine (None: nowhere it may look)."""


def local_source_finder(data_root: Path | None) -> SourceFinder:
    """What a person importing on their own machine may read: a path recorded inside the exporter's data
    root is looked for inside ``data_root`` (never outside it), an absolute path where it is."""

    def find(recorded: str) -> Path | None:
        if Path(recorded).is_absolute():
            return Path(recorded)
        if data_root is None:
            return None
        root = data_root.expanduser().resolve()
        inside = (root / recorded).resolve()
        return inside if inside.is_relative_to(root) else None

    return find


def locate_sources(records: Any, count: int, find_source: SourceFinder | None, where: str) -> list[Path]:
    """The local folder (or file) of each scan source a bundle without scans records.

    Each source is looked for first under its path inside the exporter's data root, then under its
    absolute path, each only where ``find_source`` allows; it is taken where every recorded file is
    present with its size and sha256. Otherwise :class:`BundleError` names the source and what is
    missing or different there (nothing is written).
    """
    if not isinstance(records, list) or len(records) != count:
        raise BundleError(
            where,
            f"bundle was exported without its scans and {MANIFEST} does not record them; export it with its scans",
        )
    if find_source is None:
        raise BundleError(
            where, "the bundle's scans are not in it and this importer may not look for them; export it with its scans"
        )
    found = []
    for k, record in enumerate(records):
        files = _recorded_files(record, k, where)
        problems: list[str] = []
        recorded = [record.get(key) for key in ("data_root_path", "path")]
        places = [p for p in recorded if isinstance(p, str) and p]
        for place in places:
            local = find_source(place)
            if local is None:
                continue
            problem = _source_problem(local, record.get("kind") == "file", files)
            if problem is None:
                found.append(local)
                break
            problems.append(f"{place}: {problem}")
        else:
            tried = "; ".join(problems) if problems else f"none of {places} may be read here"
            raise BundleError(
                where, f"scan source {k} is not in the bundle and was not found ({tried}); nothing imported"
            )
    return found


def _recorded_files(record: Any, k: int, where: str) -> dict[str, tuple[str, int]]:
    items = record.get("files") if isinstance(record, dict) else None
    if not isinstance(items, list) or not items:
        raise BundleError(where, f"{MANIFEST}: sources[{k}] lists no files")
    files: dict[str, tuple[str, int]] = {}
    for item in items:
        name = item.get("path") if isinstance(item, dict) else None
        digest, size = (item.get("sha256"), item.get("bytes")) if isinstance(item, dict) else (None, None)
        if not isinstance(name, str) or safe_member_name(name) is None or not isinstance(digest, str):
            raise BundleError(where, f"{MANIFEST}: sources[{k}] has a file without a usable path or sha256")
        if not isinstance(size, int) or isinstance(size, bool):
            raise BundleError(where, f"{MANIFEST}: sources[{k}] file '{name}' needs its size in bytes")
        files[name] = (digest.lower(), size)
    return files


def _source_problem(local: Path, single_file: bool, files: dict[str, tuple[str, int]]) -> str | None:
    """What keeps ``local`` from being the recorded source (a missing or different file), or None."""
    if single_file:
        if not local.is_file():
            return "no such file"
        present = {local.name: local}
    else:
        if not local.is_dir():
            return "no such folder"
        present = {name: path for name, path in _files_of_source(local)}
    missing = sorted(set(files) - set(present))
    if missing:
        return f"missing {', '.join(missing[:3])}" + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
    for name, (digest, size) in sorted(files.items()):
        if present[name].stat().st_size != size or _sha256(present[name]) != digest:
            return f"'{name}' differs from the exported file (sha256)"
    return None
