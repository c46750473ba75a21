"""PLY point clouds (ASCII and binary), read with our own header parser.

General-purpose libraries return an empty cloud for a damaged PLY without saying why; a scan that
silently vanishes from a map is worse than an error, so the header is validated here and truncated
or malformed bodies are reported with the file (and, for ASCII, the line). Coordinates are taken
as-is (metres, canonical frame); y-up datasets such as the Stanford bunny go through the ``conf``
format, which carries the y-up convention.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import read_file_bytes
from slam6d.io.text import parse_numeric_rows

_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_BYTE_ORDERS = {"binary_little_endian": "<", "binary_big_endian": ">"}
_ENCODINGS = ("ascii", *_BYTE_ORDERS)
INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance", "remission")


@dataclass
class PlyProperty:
    name: str
    dtype: str
    list_count: str | None = None  # count type of a list property


@dataclass
class PlyElement:
    name: str
    count: int
    properties: list[PlyProperty] = field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.list_count is not None for p in self.properties)

    def record_dtype(self, byte_order: str) -> np.dtype:
        return np.dtype([(p.name, byte_order + p.dtype) for p in self.properties])


@dataclass
class PlyHeader:
    encoding: str
    elements: list[PlyElement]
    body_offset: int  # byte offset of the body
    header_lines: int  # number of lines up to and including end_header


def parse_ply_header(path: Path, raw: bytes) -> PlyHeader:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise FormatError(path, "not a PLY file (must start with 'ply' and have an 'end_header' line)")
    newline = raw.find(b"\n", end)
    body_offset = len(raw) if newline < 0 else newline + 1
    try:
        lines = raw[:body_offset].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise FormatError(path, "PLY header is not ASCII text") from None
    encoding: str | None = None
    elements: list[PlyElement] = []
    for line_no, line in enumerate(lines, start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info", "end_header"):
            continue
        if words[0] == "format":
            if len(words) != 3 or words[1] not in _ENCODINGS:
                raise FormatError(
                    path,
                    "unknown PLY format line (expected: format ascii|binary_little_endian|binary_big_endian VERSION)",
                    line_no,
                )
            encoding = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise FormatError(path, "bad element line (expected: element NAME COUNT)", line_no)
            elements.append(PlyElement(words[1], int(words[2])))
        elif words[0] == "property":
            if not elements:
                raise FormatError(path, "property before any element", line_no)
            if len(words) == 5 and words[1] == "list" and words[2] in _TYPES and words[3] in _TYPES:
                elements[-1].properties.append(PlyProperty(words[4], _TYPES[words[3]], _TYPES[words[2]]))
            elif len(words) == 3 and words[1] in _TYPES:
                elements[-1].properties.append(PlyProperty(words[2], _TYPES[words[1]]))
            else:
                raise FormatError(
                    path, "bad property line (expected: property TYPE NAME or property list TYPE TYPE NAME)", line_no
                )
        else:
            raise FormatError(
                path, "unexpected PLY header keyword (expected format, element, property, comment, obj_info)", line_no
            )
    if encoding is None:
        raise FormatError(path, "PLY header has no 'format' line")
    return PlyHeader(encoding, elements, body_offset, len(lines))


def _vertex_element(path: Path, header: PlyHeader) -> tuple[int, PlyElement]:
    for index, element in enumerate(header.elements):
        if element.name == "vertex":
            names = [p.name for p in element.properties]
            missing = [axis for axis in "xyz" if axis not in names]
            if missing:
                raise FormatError(path, f"vertex element lacks propert{'ies' if len(missing) > 1 else 'y'} {missing}")
            if element.has_lists:
                raise FormatError(path, "list properties inside the vertex element are not supported")
            return index, element
    raise FormatError(path, "PLY file has no 'vertex' element")


def _intensity_name(element: PlyElement) -> str | None:
    for prop in element.properties:
        if prop.name.lower() in INTENSITY_NAMES:
            return prop.name
    return None


def _read_ascii(path: Path, raw: bytes, header: PlyHeader, index: int, vertex: PlyElement) -> NDArray[np.float64]:
    try:
        lines = raw[header.body_offset :].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise FormatError(path, "ASCII PLY body contains non-ASCII bytes") from None
    skip = sum(e.count for e in header.elements[:index])  # one line per element instance
    body = lines[skip : skip + vertex.count]
    if len(body) < vertex.count:
        raise FormatError(
            path,
            f"truncated: header promises {vertex.count} vertices, found {max(len(body), 0)}",
            header.header_lines + skip + len(body) + 1,
        )
    first = header.header_lines + skip + 1
    rows = parse_numeric_rows(path, "\n".join(body), (len(vertex.properties),), first_line=first)
    if rows.shape[0] != vertex.count:  # blank lines inside the vertex block shift everything after them
        raise FormatError(path, f"{vertex.count - rows.shape[0]} blank line(s) inside the vertex block", first)
    return rows


def _read_binary(path: Path, raw: bytes, header: PlyHeader, index: int, vertex: PlyElement) -> np.ndarray:
    order = _BYTE_ORDERS[header.encoding]
    offset = header.body_offset
    for element in header.elements[:index]:
        if element.has_lists:
            raise FormatError(path, f"binary element '{element.name}' with lists before the vertices is not supported")
        offset += element.count * element.record_dtype(order).itemsize
    dtype = vertex.record_dtype(order)
    needed = vertex.count * dtype.itemsize
    if len(raw) - offset < needed:
        raise FormatError(
            path,
            f"truncated: header promises {vertex.count} vertices ({needed} bytes), only {max(len(raw) - offset, 0)} "
            "bytes follow",
        )
    return np.frombuffer(raw, dtype=dtype, count=vertex.count, offset=offset)


def read_ply(path: Path) -> CloudData:
    """PLY (ASCII or binary) vertices x y z [intensity], metres, z up"""
    raw = read_file_bytes(path)
    header = parse_ply_header(path, raw)
    index, vertex = _vertex_element(path, header)
    names = [p.name for p in vertex.properties]
    intensity_name = _intensity_name(vertex)
    if header.encoding == "ascii":
        rows = _read_ascii(path, raw, header, index, vertex)
        points = rows[:, [names.index(a) for a in "xyz"]]
        intensity = rows[:, names.index(intensity_name)] if intensity_name else None
    else:
        records = _read_binary(path, raw, header, index, vertex)
        points = np.stack([records[a].astype(np.float64) for a in "xyz"], axis=1)
        intensity = records[intensity_name] if intensity_name else None
    return CloudData(points, None if intensity is None else np.asarray(intensity, dtype=np.float32))


def write_ply(
    path: Path | str,
    points: NDArray[np.float64],
    colors: NDArray[np.uint8] | None = None,
    intensity: NDArray[np.floating] | None = None,
    binary: bool = True,
) -> None:
    """Write points (double precision, so georeferenced coordinates keep their millimetres)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fields: list[tuple[str, str]] = [("x", "f8"), ("y", "f8"), ("z", "f8")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if intensity is not None:
        fields.append(("intensity", "f4"))
    records = np.zeros(len(points), dtype=np.dtype([(n, "<" + t) for n, t in fields]))
    for axis, name in enumerate("xyz"):
        records[name] = points[:, axis]
    if colors is not None:
        rgb = np.asarray(colors).reshape(-1, 3)
        for axis, name in enumerate(("red", "green", "blue")):
            records[name] = rgb[:, axis]
    if intensity is not None:
        records["intensity"] = np.asarray(intensity).reshape(-1)
    type_names = {"f8": "double", "f4": "float", "u1": "uchar"}
    encoding = "binary_little_endian" if binary else "ascii"
    header = [f"ply\nformat {encoding} 1.0\nelement vertex {len(points)}\n"]
    header += [f"property {type_names[t]} {n}\n" for n, t in fields]
    header.append("end_header\n")
    with Path(path).open("wb") as fh:
        fh.write("".join(header).encode("ascii"))
        if binary:
            fh.write(records.tobytes())  # fields are declared little-endian, whatever the host
        else:
            formats = ["%.17g" if t == "f8" else "%d" if t == "u1" else "%.9g" for _, t in fields]
            if len(points):
                np.savetxt(fh, np.column_stack([records[n].astype(np.float64) for n, _ in fields]), fmt=formats)


PLY_FORMAT = register_format(ScanFormat("ply", read_ply))
