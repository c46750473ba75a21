"""PCL ``.pcd`` point clouds: ``DATA ascii``, ``binary`` and ``binary_compressed``.

Parsed here rather than through a general library so that a truncated or malformed file is an
error naming the file (and line), not an empty cloud. ``binary_compressed`` bodies are LZF
compressed and stored field by field; the decompressor is compiled with numba on first use. The
header's ``VIEWPOINT`` (sensor pose, ``tx ty tz qw qx qy qz``) becomes the scan's pose when it is
not the identity. Coordinates are taken as metres in the canonical frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.geometry import Matrix, make_pose, quaternion_to_rotation, rotation_to_quaternion
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import read_file_bytes
from slam6d.io.text import parse_numeric_rows

_HEADER_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_TYPE_CODES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}
_TYPE_CODES |= {("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}
INTENSITY_NAMES = ("intensity", "i", "reflectance")
# An LZF back-reference of 3 bytes stands for at most 264: no stream expands more than ~88-fold, so a
# size word claiming more is damaged (and would allocate that much before decoding failed).
_LZF_MAX_EXPANSION = 90
# PCL's widest point types (SHOT descriptors) take ~5.4 kB; a COUNT making a record larger than this
# is damaged (a 2^64 COUNT made numpy's record type itself fail).
_MAX_RECORD_BYTES = 1 << 20


@dataclass
class PcdHeader:
    fields: list[str]
    dtypes: list[str]
    counts: list[int]
    points: int
    viewpoint: NDArray[np.float64]
    data: str
    body_offset: int
    header_lines: int

    def record_dtype(self) -> np.dtype:
        return np.dtype(
            [
                (name if name != "_" else f"_pad{i}", "<" + dt, (n,) if n > 1 else ())
                for i, (name, dt, n) in enumerate(zip(self.fields, self.dtypes, self.counts, strict=True))
            ]
        )


def parse_pcd_header(path: Path, raw: bytes) -> PcdHeader:
    values: dict[str, list[str]] = {}
    offset = 0
    line_no = 0
    while "DATA" not in values:
        newline = raw.find(b"\n", offset)
        if newline < 0:
            raise FormatError(path, "PCD header ends before its DATA line", line_no + 1)
        line_no += 1
        try:
            line = raw[offset:newline].decode("ascii").strip()
        except UnicodeDecodeError:
            raise FormatError(path, "PCD header is not ASCII text (not a PCD file?)", line_no) from None
        offset = newline + 1
        if not line or line.startswith("#"):
            continue
        key, *rest = line.split()
        if key not in _HEADER_KEYS:
            raise FormatError(
                path, f"unexpected PCD header keyword (expected one of {', '.join(_HEADER_KEYS)})", line_no
            )
        values[key] = rest
        if key in ("WIDTH", "HEIGHT", "POINTS") and (len(rest) != 1 or not rest[0].isdigit()):
            raise FormatError(path, f"{key} must be one non-negative integer", line_no)
        if key == "DATA" and rest not in (["ascii"], ["binary"], ["binary_compressed"]):
            raise FormatError(path, "unknown DATA (expected ascii, binary or binary_compressed)", line_no)
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH"):
        if key not in values:
            raise FormatError(path, f"PCD header lacks {key}")
    fields = values["FIELDS"]
    counts_text = values.get("COUNT", ["1"] * len(fields))
    if not len(fields) == len(values["SIZE"]) == len(values["TYPE"]) == len(counts_text):
        raise FormatError(path, "FIELDS, SIZE, TYPE and COUNT must have the same number of entries")
    try:
        sizes = [int(s) for s in values["SIZE"]]
        counts = [int(c) for c in counts_text]
        viewpoint = np.array([float(v) for v in values.get("VIEWPOINT", ["0", "0", "0", "1", "0", "0", "0"])])
    except ValueError:
        raise FormatError(path, "SIZE, COUNT and VIEWPOINT must be numbers") from None
    dtypes = []
    for kind, size in zip(values["TYPE"], sizes, strict=True):
        if (kind, size) not in _TYPE_CODES:
            raise FormatError(path, "unsupported TYPE and SIZE combination (F 4/8, I or U 1/2/4/8)")
        dtypes.append(_TYPE_CODES[(kind, size)])
    if min(counts) < 1 or sum(size * count for size, count in zip(sizes, counts, strict=True)) > _MAX_RECORD_BYTES:
        raise FormatError(
            path, f"COUNT entries must be at least 1 and a point's record at most {_MAX_RECORD_BYTES:,} bytes"
        )
    if viewpoint.shape != (7,):
        raise FormatError(path, "VIEWPOINT needs 7 numbers (tx ty tz qw qx qy qz)")
    width = int(values["WIDTH"][0])
    height = int(values.get("HEIGHT", ["1"])[0])
    points = int(values["POINTS"][0]) if "POINTS" in values else width * height
    if missing := [axis for axis in "xyz" if axis not in fields]:
        raise FormatError(path, f"PCD has no field(s) {missing}")
    return PcdHeader(fields, dtypes, counts, points, viewpoint, values["DATA"][0], offset, line_no)


def lzf_decompress(path: Path, compressed: bytes, size: int) -> bytes:
    from slam6d.io.lzf import decompress  # numba import and compile only when a compressed file shows up

    out = np.empty(size, dtype=np.uint8)
    written = decompress(np.frombuffer(compressed, dtype=np.uint8), out)
    if written != size:
        raise FormatError(path, f"corrupt binary_compressed body (LZF data decodes to {written} of {size} bytes)")
    return out.tobytes()


def _records(path: Path, raw: bytes, header: PcdHeader) -> np.ndarray:
    dtype = header.record_dtype()
    body = memoryview(raw)[header.body_offset :]
    if header.data == "ascii":
        try:
            text = bytes(body).decode("ascii")
        except UnicodeDecodeError:
            raise FormatError(path, "ASCII PCD body contains non-ASCII bytes") from None
        rows = parse_numeric_rows(path, text, (sum(header.counts),), first_line=header.header_lines + 1)
        if rows.shape[0] != header.points:
            raise FormatError(
                path,
                f"header promises {header.points} points, body has {rows.shape[0]}",
                header.header_lines + rows.shape[0] + 1,
            )
        records = np.zeros(header.points, dtype=dtype)
        first = 0
        for name in dtype.names or ():
            width = int(np.prod(dtype[name].shape)) if dtype[name].shape else 1
            records[name] = rows[:, first : first + width].reshape(records[name].shape)
            first += width
        return records
    needed = header.points * dtype.itemsize
    if header.data == "binary":
        if len(body) < needed:
            raise FormatError(path, f"truncated: {header.points} points need {needed} bytes, {len(body)} follow")
        return np.frombuffer(body, dtype=dtype, count=header.points)
    if len(body) < 8:
        raise FormatError(path, "truncated: binary_compressed body lacks its size words")
    compressed_size, size = (int(v) for v in np.frombuffer(body, dtype="<u4", count=2))
    if size != needed:
        raise FormatError(path, f"binary_compressed body decodes to {size} bytes, header implies {needed}")
    if len(body) - 8 < compressed_size:
        raise FormatError(path, f"truncated: compressed body is {len(body) - 8} of {compressed_size} bytes")
    if size > _LZF_MAX_EXPANSION * compressed_size + 64:
        raise FormatError(path, f"binary_compressed body cannot decode to {size:,} bytes from {compressed_size:,}")
    data = lzf_decompress(path, bytes(body[8 : 8 + compressed_size]), size) if size else b""
    # Field by field (struct of arrays) on disk: reassemble into records.
    records = np.zeros(header.points, dtype=dtype)
    offset = 0
    for name in dtype.names or ():
        field_dtype = dtype[name]
        nbytes = header.points * field_dtype.itemsize
        count = header.points * (field_dtype.itemsize // field_dtype.base.itemsize)
        column = np.frombuffer(data, dtype=field_dtype.base, count=count, offset=offset)
        records[name] = column.reshape(records[name].shape)
        offset += nbytes
    return records


def _viewpoint_pose(viewpoint: NDArray[np.float64]) -> Matrix | None:
    pose = make_pose(quaternion_to_rotation(viewpoint[3:7]), viewpoint[:3])
    return None if np.allclose(pose, np.eye(4)) else pose


def read_pcd(path: Path) -> CloudData:
    """PCL .pcd (ascii, binary, binary_compressed) x y z [intensity], metres; VIEWPOINT = pose"""
    raw = read_file_bytes(path)
    header = parse_pcd_header(path, raw)
    records = _records(path, raw, header)
    points = np.stack([records[a].astype(np.float64) for a in "xyz"], axis=1).reshape(-1, 3)
    name = next((f for f in header.fields if f.lower() in INTENSITY_NAMES), None)
    intensity = records[name].astype(np.float32).reshape(-1) if name else None
    return CloudData(points, intensity, _viewpoint_pose(header.viewpoint))


def write_pcd(
    path: Path | str,
    points: NDArray[np.float64],
    intensity: NDArray[np.floating] | None = None,
    binary: bool = True,
    viewpoint: Matrix | None = None,
) -> None:
    """PCD with float32 x y z [intensity] (what PCL tools expect), ``DATA binary`` or ``ascii``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fields = ["x", "y", "z"] + (["intensity"] if intensity is not None else [])
    records = np.zeros(len(points), dtype=np.dtype([(f, "<f4") for f in fields]))
    for axis, name in enumerate("xyz"):
        records[name] = points[:, axis]
    if intensity is not None:
        records["intensity"] = np.asarray(intensity).reshape(-1)
    pose = np.eye(4) if viewpoint is None else np.asarray(viewpoint)
    q = rotation_to_quaternion(pose[:3, :3])
    vp = " ".join(f"{v:.9g}" for v in (*pose[:3, 3], *q))
    n = len(fields)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\nSIZE {' '.join(['4'] * n)}\nTYPE {' '.join(['F'] * n)}\n"
        f"COUNT {' '.join(['1'] * n)}\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT {vp}\nPOINTS {len(points)}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    with Path(path).open("wb") as fh:
        fh.write(header.encode("ascii"))
        if binary:
            fh.write(records.tobytes())
        elif len(points):
            np.savetxt(fh, np.column_stack([records[f] for f in fields]), fmt="%.9g")


PCD_FORMAT = register_format(ScanFormat("pcd", read_pcd))
