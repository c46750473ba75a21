"""Unpacking zip archives from strangers: every limit checked while the bytes stream, nothing kept on refusal.

A zip's directory can lie (sizes, names), so nothing it declares is trusted: each entry is read in
chunks and counted as it expands - total size, size against its compressed size (ratio), entry
count - and refused the moment a limit is crossed, before the next chunk is written. Names that
would land outside the destination (``../``, absolute paths, drive letters, backslashes), links and
other non-regular entries, nested archives (by name and by their first bytes), encrypted entries
and bad CRCs are refused with a message naming the entry. Everything is written into a temporary
folder beside the destination and moved into place only when the whole archive passed, so a
refused archive leaves nothing behind.

Uploads of scans (:mod:`app.workbench`) and session bundles (:mod:`slam6d.bundle`) both unpack here.
"""

from __future__ import annotations

import os
import shutil
import stat
import tempfile
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from slam6d.errors import FormatError

_CHUNK = 1 << 20
# First bytes of the compressed and archive formats a nested bomb would use.
_ARCHIVE_MAGIC = (
    b"PK\x03\x04",  # zip (also docx, jar, npz)
    b"PK\x05\x06",  # empty zip
    b"\x1f\x8b",  # gzip
    b"BZh",  # bzip2
    b"\xfd7zXZ\x00",  # xz
    b"7z\xbc\xaf\x27\x1c",  # 7-zip
    b"Rar!\x1a\x07",  # rar
    b"\x28\xb5\x2f\xfd",  # zstandard
)
_ARCHIVE_SUFFIXES = (".zip", ".gz", ".tgz", ".tar", ".bz2", ".xz", ".7z", ".rar", ".zst", ".npz", ".jar")


@dataclass(frozen=True)
class ArchiveLimits:
    """What one archive may expand to.

    ``max_ratio`` applies to an entry once it has expanded past ``ratio_floor_bytes`` (a tiny file of
    zeros compresses a thousandfold and harms no one); scans compress 1.2-5 fold, deflate's own
    maximum is about 1,030.
    """

    max_total_bytes: int = 2 << 30
    max_entries: int = 10_000
    max_ratio: float = 100.0
    ratio_floor_bytes: int = 1 << 20


class ArchiveError(FormatError):
    """An archive was refused; ``too_large`` tells a size limit (HTTP 413) from a malformed archive (422)."""

    def __init__(self, path: Path | str, message: str, too_large: bool = False) -> None:
        self.too_large = too_large
        super().__init__(path, message)


def safe_member_name(name: str) -> PurePosixPath | None:
    """The entry's relative path if it stays inside the destination, else None.

    Refused: empty names, absolute paths (``/x``, ``\\x``, ``C:x``), any ``..`` or ``.`` step,
    backslashes (a Windows path separator that POSIX would keep as part of a name) and control
    characters.
    """
    if not name or "\\" in name or name.startswith("/") or any(ord(c) < 32 for c in name):
        return None
    path = PurePosixPath(name)
    parts = path.parts
    if not parts or any(p in ("..", ".", "") for p in parts) or (len(parts[0]) >= 2 and parts[0][1] == ":"):
        return None
    return path


def _entry_kind(info: zipfile.ZipInfo) -> str:
    """'file', 'dir', or what else the entry's Unix mode says it is (a link, a device, a FIFO)."""
    mode = info.external_attr >> 16
    if info.is_dir():
        return "dir"
    if stat.S_IFMT(mode) == 0 or stat.S_ISREG(mode):  # no type bits: written by a tool that sets permissions only
        return "file"
    if stat.S_ISLNK(mode):
        return "symbolic link"
    if stat.S_ISDIR(mode):
        return "dir"
    return "special file"


def extract_zip(
    archive: Path | BinaryIO,
    destination: Path,
    limits: ArchiveLimits = ArchiveLimits(),
    rename: Callable[[PurePosixPath], PurePosixPath | None] | None = None,
    label: str | None = None,
) -> list[PurePosixPath]:
    """Unpack ``archive`` into ``destination`` (which must not exist yet); the relative paths written.

    ``rename`` maps each entry's safe relative path to where it goes (None skips it, e.g. to flatten
    an upload's folders or drop ``__MACOSX``). ``label`` names the archive in messages (an upload's
    file name rather than its spool file). On any refusal :class:`ArchiveError` is raised and
    nothing is left at ``destination``.
    """
    where = label or (str(archive) if isinstance(archive, Path) else "archive")
    destination = Path(destination)
    if destination.exists():
        raise ArchiveError(where, f"will not unpack over {destination}, which exists")
    destination.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{destination.name}.", dir=destination.parent))
    try:
        written = _extract_into(archive, staging, limits, rename, where)
        os.replace(staging, destination)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return written


def _extract_into(
    archive: Path | BinaryIO,
    into: Path,
    limits: ArchiveLimits,
    rename: Callable[[PurePosixPath], PurePosixPath | None] | None,
    where: str,
) -> list[PurePosixPath]:
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError):
        raise ArchiveError(where, "not a valid zip archive") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > limits.max_entries:
            raise ArchiveError(where, f"holds {len(infos)} entries, more than the limit of {limits.max_entries}", True)
        total = 0
        written: list[PurePosixPath] = []
        seen: set[str] = set()
        for info in infos:
            name = safe_member_name(info.filename)
            if name is None:
                raise ArchiveError(where, f"entry {info.filename!r} has an unsafe path (absolute, '..' or backslash)")
            kind = _entry_kind(info)
            if kind == "dir":
                continue
            if kind != "file":
                raise ArchiveError(where, f"entry '{name}' is a {kind}; only regular files are accepted")
            if info.flag_bits & 0x1:
                raise ArchiveError(where, f"entry '{name}' is encrypted")
            if name.suffix.lower() in _ARCHIVE_SUFFIXES:
                raise ArchiveError(where, f"entry '{name}' is an archive itself; nested archives are not accepted")
            target = rename(name) if rename is not None else name
            if target is None:
                continue
            key = target.as_posix().lower()  # case-insensitive file systems would merge these
            if key in seen:
                raise ArchiveError(where, f"entry '{target}' appears twice")
            seen.add(key)
            total = _copy_entry(zf, info, into / target, total, limits, where, str(name))
            written.append(target)
        return written


def _copy_entry(
    zf: zipfile.ZipFile, info: zipfile.ZipInfo, out_path: Path, total: int, limits: ArchiveLimits, where: str, name: str
) -> int:
    """Stream one entry to ``out_path`` checking every limit per chunk; the new running total."""
    out_path.parent.mkdir(parents=True, exist_ok=True)
    size = 0
    compressed = max(info.compress_size, 1)
    try:
        with zf.open(info) as source, open(out_path, "xb") as sink:
            while chunk := source.read(_CHUNK):
                if size == 0 and chunk.startswith(_ARCHIVE_MAGIC):
                    raise ArchiveError(where, f"entry '{name}' is an archive itself; nested archives are not accepted")
                size += len(chunk)
                total += len(chunk)
                if total > limits.max_total_bytes:
                    raise ArchiveError(
                        where, f"expands to more than the limit of {limits.max_total_bytes // 2**20} MiB", True
                    )
                if size > limits.ratio_floor_bytes and size / compressed > limits.max_ratio:
                    raise ArchiveError(
                        where,
                        f"entry '{name}' expands more than {limits.max_ratio:g} times its compressed size"
                        " (a zip bomb?)",
                        True,
                    )
                sink.write(chunk)
    except zipfile.BadZipFile as exc:  # bad CRC, truncated data, mismatching local header
        raise ArchiveError(where, f"entry '{name}' is damaged ({exc})") from None
    except (zlib.error, EOFError, OSError, ValueError, NotImplementedError, RuntimeError) as exc:
        if isinstance(exc, FileExistsError):
            raise ArchiveError(where, f"entry '{name}' appears twice") from None
        raise ArchiveError(where, f"entry '{name}' cannot be read ({type(exc).__name__})") from None
    return total
