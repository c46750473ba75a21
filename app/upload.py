"""Sessions made from uploaded files: copied in chunks under one size budget, zips unpacked safely,
every scan proven to parse before the session exists.

An upload is hostile until proven otherwise: names are restricted to a plain alphabet, zips go
through :func:`slam6d.archive.extract_zip` (sizes, ratio, names, links and nested archives checked
while streaming), and the scans are parsed in a child process under a time limit
(:mod:`app.parse_worker`). Whatever fails, the half-made session folder is removed.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from app.errors import UploadError
from app.parse_worker import parse_session_scans
from slam6d.archive import ArchiveLimits, extract_zip
from slam6d.session import Session, reserve_session_folder

_UPLOAD_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,199}$")


@dataclass(frozen=True)
class UploadLimits:
    """What one upload may take: bytes over all its files (zips expanded), and seconds to parse."""

    max_bytes: int
    parse_timeout_s: float


def session_from_upload(
    sessions_dir: Path,
    name: str,
    files: Iterable[tuple[str, BinaryIO]],
    limits: UploadLimits,
    format_name: str | None = None,
    frame: str | None = None,
) -> Session:
    """Store uploaded scan files (or .zips of them) in a new session and prove they all parse.

    Files are copied from their (spooled) streams in chunks and zips unpacked by
    :func:`slam6d.archive.extract_zip` (sizes, ratio, names, links, nested archives checked while
    streaming); the whole upload shares one size budget. Called off the event loop; the scans are
    parsed in a child process under the parse time limit (:mod:`app.parse_worker`). On any
    problem the half-made folder is removed: a refused upload leaves nothing behind.
    """
    folder = reserve_session_folder(sessions_dir, name)
    scans = folder / "scans"
    try:
        scans.mkdir()
        budget = limits.max_bytes
        for filename, stream in files:
            base = PurePosixPath(filename.replace("\\", "/")).name
            if base.lower().endswith(".zip"):
                budget -= _unzip_upload(base, stream, folder, scans, budget)
            else:
                budget -= _copy_upload(_upload_name(base, filename), stream, scans, budget, limits.max_bytes)
        if not any(scans.iterdir()):
            raise UploadError("the upload contains no files")
        Session.create(folder, name, "scans", format_name, frame)
        # parses every scan (a bad file is reported now, with its name and line) under the time limit
        parse_session_scans(folder, limits.parse_timeout_s, f"upload '{name}'")
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return Session.open(folder)


def check_parses(session: Session, parse_timeout_s: float, label: str) -> Session:
    """Parse a new session's scans in a child process under the time limit (an import's, as an
    upload's); on any problem the session folder is removed, so a refused one leaves nothing behind."""
    try:
        parse_session_scans(session.folder, parse_timeout_s, label)
    except BaseException:
        shutil.rmtree(session.folder, ignore_errors=True)
        raise
    return Session.open(session.folder)


def _unzip_upload(base: str, stream: BinaryIO, folder: Path, scans: Path, budget: int) -> int:
    """Unpack one uploaded zip into ``scans`` (folders flattened); the bytes it took from ``budget``."""
    staging = folder / f".unzip-{len(list(folder.iterdir()))}"
    limits = ArchiveLimits(max_total_bytes=max(budget, 0))
    written = extract_zip(stream, staging, limits, rename=_flatten, label=base)
    used = 0
    for member in written:
        target = scans / member.name
        if target.exists():
            raise UploadError(f"file '{member.name}' appears twice in the upload")
        used += (staging / member).stat().st_size
        (staging / member).replace(target)
    shutil.rmtree(staging, ignore_errors=True)
    return used


def _upload_name(base: str, filename: str) -> str:
    if not _UPLOAD_NAME.match(base):
        raise UploadError(
            "file name not allowed: an uploaded file name may hold letters, digits, '.', '_' and '-' only"
        )
    return base


def _flatten(member: PurePosixPath) -> PurePosixPath | None:
    """Where a zip entry of an upload goes: its base name (folders flattened); hidden files and macOS
    resource forks skipped."""
    if member.name.startswith(".") or "__MACOSX" in member.parts:
        return None
    return PurePosixPath(_upload_name(member.name, str(member)))


def _copy_upload(name: str, stream: BinaryIO, scans: Path, budget: int, limit: int) -> int:
    """Copy one uploaded file into ``scans`` in chunks, refusing (413) once ``budget`` is spent."""
    target = scans / name
    if target.exists():
        raise UploadError(f"file '{name}' appears twice in the upload")
    copied = 0
    with open(target, "xb") as sink:
        while chunk := stream.read(1 << 20):
            copied += len(chunk)
            if copied > budget:
                raise UploadError(f"upload exceeds the limit of {limit // 2**20} MiB", 413)
            sink.write(chunk)
    return copied
