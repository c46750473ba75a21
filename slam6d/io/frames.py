"""3DTK ``.frames`` files: the pose history of one scan, as 3DTK's viewer (``show``) replays it.

One line per recorded step: the 4x4 pose in column-major (OpenGL) order - translation in entries
13-15 - followed by a type flag telling the viewer which stage produced it. The last line is the
final pose. Poses are in the scan format's native frame (for uos: centimetres, left-handed), so
files we write can be loaded by 3DTK beside its own output and compared line by line.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import IntEnum
from pathlib import Path

import numpy as np

from slam6d.errors import FormatError
from slam6d.geometry import FrameConvention, Matrix
from slam6d.io.text import parse_numeric_rows, read_text_file


class FrameType(IntEnum):
    """The stage that produced a pose; 3DTK's viewer colours scans by it."""

    INVALID = 0
    ICP = 1
    ICP_INACTIVE = 2
    LUM = 3
    ELCH = 4


FrameEntry = tuple[Matrix, FrameType]


def read_frames(path: Path | str) -> list[FrameEntry]:
    """All (native 4x4 pose, type) entries of a ``.frames`` file, oldest first."""
    path = Path(path)
    text = read_text_file(path, "17 numbers per line")
    rows = parse_numeric_rows(path, text, allowed_columns=(17,))
    if rows.shape[0] == 0:
        raise FormatError(path, "the file contains no frames")
    entries: list[FrameEntry] = []
    line_numbers = [
        n for n, ln in enumerate(text.splitlines(), start=1) if ln.strip() and not ln.lstrip().startswith("#")
    ]
    for row, line_no in zip(rows, line_numbers, strict=True):
        if not np.isfinite(row).all():
            raise FormatError(path, "frame contains NaN or infinity", line_no)
        pose = row[:16].reshape(4, 4).T  # column-major on disk
        if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
            raise FormatError(
                path, "not a 4x4 rigid transform in column-major order (entries 4, 8, 12 must be 0)", line_no
            )
        try:
            flag = FrameType(int(row[16]))
        except ValueError:
            raise FormatError(path, f"unknown frame type {row[16]:g} (expected 0-4)", line_no) from None
        entries.append((pose, flag))
    return entries


def final_frame_pose(path: Path | str) -> Matrix:
    """The pose 3DTK ended with: the last line."""
    return read_frames(path)[-1][0]


_FRAME_LINE = " ".join(["%.9g"] * 16) + " %d\n"
"""One ``.frames`` line: the 16 numbers (9 significant digits) and the flag. One ``%`` per line, not a
format per number: a run writes a line per ICP iteration of every scan (1,200-1,500 on a 30-scan
walk), and formatting them number by number was 0.1 s of its CPU."""


def write_frames(path: Path | str, entries: Sequence[tuple[Matrix, int]]) -> None:
    """Write native poses with their type flags, one line each, as 3DTK does."""
    with Path(path).open("w") as fh:
        for pose, flag in entries:
            values = np.asarray(pose, dtype=np.float64).T.reshape(16).tolist()
            fh.write(_FRAME_LINE % (*values, int(FrameType(flag))))


def write_sequence_frames(
    directory: Path | str,
    histories: Sequence[Sequence[tuple[Matrix, int]]],
    convention: FrameConvention,
    names: Sequence[str] | None = None,
) -> list[Path]:
    """One ``.frames`` file per scan from canonical pose histories, converted back to the input's frame.

    Files are named after the scans (``scan000.frames`` for uos input) so 3DTK's viewer finds them
    beside the ``.3d`` files.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for index, history in enumerate(histories):
        name = names[index] if names is not None else f"scan{index:03d}"
        path = directory / f"{name}.frames"
        write_frames(path, [(convention.pose_to_native(np.asarray(pose)), flag) for pose, flag in history])
        paths.append(path)
    return paths
