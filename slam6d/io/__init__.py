"""Scan and pose file formats behind one registry (see :mod:`slam6d.io.registry`)."""

from slam6d.io.registry import (
    CloudData,
    ReadOptions,
    ScanFormat,
    detect_format,
    format_names,
    get_format,
    read_scan,
    read_sequence,
    register_format,
)

__all__ = [
    "CloudData",
    "ReadOptions",
    "ScanFormat",
    "detect_format",
    "format_names",
    "get_format",
    "read_scan",
    "read_sequence",
    "register_format",
]
