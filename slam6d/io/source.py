"""Opening a scan or pose file safely: regular files only, read with a size limit.

A path handed to a reader may name anything: a device that never ends (``/dev/zero``), a FIFO
that blocks the reading thread forever, a socket, a folder, or a file far larger than any scan.
Every reader opens its file here: non-blocking (so a FIFO cannot hang the open), then checks on
the open descriptor that it is a regular file and no larger than the limit, and only then reads
it - so a hostile path is refused at once with a message naming it, before any byte is read.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from slam6d.errors import FormatError

# No scan or pose file a reader accepts is larger: a terrestrial station of 100 M points in
# binary PLY is ~2.4 GB. Bigger files are refused before they are read into memory.
MAX_FILE_BYTES = 4 << 30


def _refuse_special(path: Path, mode: int) -> None:
    if stat.S_ISREG(mode):
        return
    kind = (
        "folder"
        if stat.S_ISDIR(mode)
        else "FIFO"
        if stat.S_ISFIFO(mode)
        else "socket"
        if stat.S_ISSOCK(mode)
        else "device"
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
        else "special file"
    )
    raise FormatError(path, f"not a regular file (a {kind}); only regular files are read")


def check_regular_file(path: Path | str, limit: int = MAX_FILE_BYTES) -> int:
    """The file's size, after checking it is a regular file within ``limit`` bytes (for readers that
    hand the path to a library)."""
    path = Path(path)
    try:
        info = os.stat(path)
    except OSError as exc:
        raise FormatError(path, f"cannot read: {exc.strerror or type(exc).__name__}") from None
    _refuse_special(path, info.st_mode)
    if info.st_size > limit:
        raise FormatError(path, f"file of {info.st_size:,} bytes is larger than the limit of {limit:,}")
    return info.st_size


def read_file_bytes(path: Path | str, limit: int = MAX_FILE_BYTES) -> bytes:
    """A regular file's bytes, or :class:`FormatError` (not regular, too large, unreadable)."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise FormatError(path, f"cannot read: {exc.strerror or type(exc).__name__}") from None
    try:
        info = os.fstat(fd)
        _refuse_special(path, info.st_mode)
        if info.st_size > limit:
            raise FormatError(path, f"file of {info.st_size:,} bytes is larger than the limit of {limit:,}")
    except BaseException:
        os.close(fd)
        raise
    with os.fdopen(fd, "rb") as stream:
        try:
            data = stream.read(info.st_size)  # read(n) allocates n up front: the size, never the limit
            grown = stream.read(1)
        except OSError as exc:
            raise FormatError(path, f"cannot read: {exc.strerror or type(exc).__name__}") from None
    if grown:
        raise FormatError(path, "file grew while it was read; try again once it is complete")
    return data


def read_file_text(path: Path | str, expected: str = "", limit: int = MAX_FILE_BYTES) -> str:
    """A regular text file's contents (UTF-8); binary files are refused saying what was ``expected``."""
    data = read_file_bytes(path, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise FormatError(path, "not a text file" + (f" (expected {expected})" if expected else "")) from None
