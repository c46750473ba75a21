"""ASPRS LAS/LAZ point clouds (via laspy, LAZ through lazrs).

Coordinates are the scaled ones (``X * scale + offset``), assumed metres in a right-handed, z-up
frame - true for projected CRSs (UTM etc.); a file in feet would need converting first. Intensity
is the 16-bit LAS intensity. Points flagged withheld are still read: the flag is advisory and
scanners use it inconsistently.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import check_regular_file

_HEADER_BYTES = 375  # the LAS 1.4 public header; older versions' headers are shorter
_MIN_VLR_BYTES = 54  # a variable-length record's own header
_MIN_EVLR_BYTES = 60
# LAZ stores 5-10x smaller than LAS; a header claiming more than this many times the file is lying
# (and laspy/lazrs would allocate what it claims before finding out).
_MAX_LAZ_EXPANSION = 64


def check_las_header(path: Path, stream: BinaryIO, file_size: int) -> None:
    """Refuse a LAS/LAZ file whose public header claims what the file cannot hold.

    laspy trusts the header's point count, record length and record counts and allocates for them
    first; a damaged or hostile header (10^12 points in a 4 kB file) would exhaust memory before any
    error. Checked here from the fixed header layout (ASPRS LAS 1.0-1.4), so that only plausible
    files reach the library. LAZ files also get their chunk table checked (lazrs allocates the
    number of chunks it claims).
    """
    head = stream.read(_HEADER_BYTES)
    if len(head) < 227 or head[:4] != b"LASF":
        raise FormatError(path, "not a LAS/LAZ file (no 'LASF' header)")
    minor = head[25]
    header_size = int.from_bytes(head[94:96], "little")
    point_offset = int.from_bytes(head[96:100], "little")
    vlrs = int.from_bytes(head[100:104], "little")
    point_format = head[104]
    record_length = int.from_bytes(head[105:107], "little")
    points = int.from_bytes(head[107:111], "little")
    if minor >= 4 and len(head) >= 255 and header_size >= 375:
        points = int.from_bytes(head[247:255], "little") or points
        evlrs = int.from_bytes(head[243:247], "little")
        if evlrs * _MIN_EVLR_BYTES > file_size:
            raise FormatError(path, f"LAS header claims {evlrs:,} extended records, more than the file holds")
    if not 227 <= header_size <= point_offset <= file_size:
        raise FormatError(path, "LAS header sizes and point data offset are inconsistent (damaged file)")
    if vlrs * _MIN_VLR_BYTES > point_offset - header_size:
        raise FormatError(path, f"LAS header claims {vlrs:,} variable-length records, more than the file holds")
    if record_length < 20:
        raise FormatError(path, f"LAS point record length {record_length} is below the smallest format's 20 bytes")
    compressed = bool(point_format & 0x80) or path.suffix.lower() == ".laz"
    available = (file_size - point_offset) * (_MAX_LAZ_EXPANSION if compressed else 1)
    if points * record_length > available:
        raise FormatError(
            path,
            f"LAS header claims {points:,} points of {record_length} bytes, more than the file's "
            f"{file_size:,} bytes can hold (truncated or damaged)",
        )
    if compressed:
        _check_laz_chunk_size(path, stream, header_size, vlrs, points * record_length, record_length)
        _check_laz_chunk_table(path, stream, point_offset, file_size, points)


_LASZIP_VLR = (b"laszip encoded", 22204)
_VARIABLE_CHUNKS = 2**32 - 1  # LASzip's chunk size for chunks of varying point counts
_MAX_CHUNK_BYTES = 64 << 20  # LASzip writes 50,000 points per chunk: at most 3.3 MB of records


def _check_laz_chunk_size(
    path: Path, stream: BinaryIO, header_size: int, vlrs: int, point_bytes: int, record_length: int
) -> None:
    """The LASzip record's points per chunk must fit the file's points (or a usual chunk's size).

    lazrs allocates a whole chunk's records before decompressing it, whatever the point count says:
    a damaged chunk size of 4 x 10^9 made it abort the process asking for 85 GB.
    """
    stream.seek(header_size)
    for _ in range(vlrs):
        head = stream.read(_MIN_VLR_BYTES)
        if len(head) < _MIN_VLR_BYTES:
            return  # a truncated record list: laspy refuses it with its own error
        user_id, record_id = head[2:18].rstrip(b"\0"), int.from_bytes(head[18:20], "little")
        length = int.from_bytes(head[20:22], "little")
        if (user_id, record_id) == _LASZIP_VLR and length >= 16:
            chunk_size = int.from_bytes(stream.read(16)[12:16], "little")
            if chunk_size != _VARIABLE_CHUNKS and chunk_size * record_length > max(point_bytes, _MAX_CHUNK_BYTES):
                raise FormatError(path, f"LAZ chunk size of {chunk_size:,} points is damaged (more than the file's)")
            return
        stream.seek(length, 1)


def _check_laz_chunk_table(path: Path, stream: BinaryIO, point_offset: int, file_size: int, points: int) -> None:
    """The LAZ chunk table (its offset is the first 8 bytes of the point data) must be version 0 and
    list no more chunks than there are points or bytes."""
    stream.seek(point_offset)
    table_offset = int.from_bytes(stream.read(8), "little", signed=True)
    if table_offset == -1:  # written without a table: the reader walks the chunks
        return
    if not point_offset + 8 <= table_offset <= file_size - 8:
        raise FormatError(path, "LAZ chunk table lies outside the file (truncated or damaged)")
    stream.seek(table_offset)
    version = int.from_bytes(stream.read(4), "little")
    chunks = int.from_bytes(stream.read(4), "little")
    if version != 0 or chunks > max(points, 1) or chunks > file_size:
        raise FormatError(path, f"LAZ chunk table (version {version}, {chunks:,} chunks) is damaged")


def read_las(path: Path) -> CloudData:
    """ASPRS LAS/LAZ, scaled coordinates (m, z up) + intensity"""
    import laspy

    size = check_regular_file(path)
    with open(path, "rb") as stream:
        check_las_header(path, stream, size)
    try:
        las = laspy.read(path)
        points = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float64)
        intensity = np.asarray(las.intensity, dtype=np.float32)
    except (laspy.errors.LaspyException, RuntimeError, ValueError, OSError, EOFError, struct.error) as exc:
        # laspy's messages quote the file's bytes; only the kind of failure is told
        raise FormatError(path, f"cannot read as LAS/LAZ ({type(exc).__name__})") from None
    return CloudData(points.reshape(-1, 3), intensity.reshape(-1))


def _intensity_u16(intensity: NDArray[np.floating]) -> NDArray[np.uint16]:
    """LAS intensity is 16-bit: values in [0, 1] (KITTI style) are stretched, larger ones clipped."""
    values = np.nan_to_num(np.asarray(intensity, dtype=np.float64).reshape(-1))
    if values.size and values.max() <= 1.0:
        values = values * 65535.0
    return np.clip(np.rint(values), 0, 65535).astype(np.uint16)


def write_las(
    path: Path | str,
    points: NDArray[np.float64],
    colors: NDArray[np.uint8] | None = None,
    intensity: NDArray[np.floating] | None = None,
    scale: float = 0.0001,
) -> None:
    """LAS or LAZ (compressed when the suffix is ``.laz``) with 0.1 mm resolution by default.

    The offset is the cloud's minimum corner, so large georeferenced coordinates keep full resolution
    in LAS's 32-bit integers (a cloud may span up to 2^31 * scale = 214 km per axis).
    """
    import laspy

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    header = laspy.LasHeader(point_format=2 if colors is not None else 0, version="1.2")
    header.offsets = np.floor(points.min(axis=0)) if len(points) else np.zeros(3)
    header.scales = np.full(3, scale)
    if len(points) and np.any((points.max(axis=0) - header.offsets) / scale >= 2**31):
        raise ValueError(f"cloud too large for LAS at scale {scale} m; use a coarser scale")
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if intensity is not None:
        las.intensity = _intensity_u16(intensity)
    if colors is not None:
        rgb = np.asarray(colors, dtype=np.uint16).reshape(-1, 3) * 257  # 8 -> 16 bit, 255 -> 65535
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.write(str(path))


LAS_FORMAT = register_format(ScanFormat("las", read_las, suffixes=(".las", ".laz")))
