"""The order in which the scans of a folder are taken: natural by default, by name or by time on request.

Scanners and recording tools name scans by a counter (``0.pcd`` … ``29.pcd``) or a timestamp
(``1581234567.123456.pcd``), often without leading zeros. Sorted as plain text those come out as
0, 1, 10, 11, …, 19, 2, 20, … and sequential registration then matches scans recorded far apart.
Natural order compares each run of digits (with a decimal fraction, so timestamps with different
numbers of decimals still compare as numbers) by value and the rest as text, which is the
acquisition order for every naming scheme seen in practice. ``name`` (plain text order) and
``mtime`` (file modification time) are for the rare folder where it is not.

Formats whose order is fixed by an index (3DTK's ``scanNNN`` numbering, a Stanford ``.conf``, a
libpointmatcher list file) keep that order; asking for another one is an error, not a silent no-op.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from decimal import Decimal
from pathlib import Path

SCAN_ORDERS = ("natural", "name", "mtime")
DEFAULT_ORDER = "natural"

# a run of digits, optionally with a decimal fraction ("1581234567.25"); the suffix is never part of the name
_NUMBER = re.compile(r"(\d+(?:\.\d+)?)")

NaturalKey = tuple[tuple[int, Decimal, str], ...]


def natural_key(name: str) -> NaturalKey:
    """Sort key of a file name: numbers by value, text case-insensitively, the suffix ignored.

    ``2.pcd`` < ``10.pcd``, and ``1581234567.25.pcd`` < ``1581234567.5.pcd``: fractions compare as
    decimals, as timestamps must. Equal keys (``7.pcd`` and ``007.pcd``) are separated by the
    callers' tie-break on the plain name.
    """
    stem = name.rsplit(".", 1)[0] if "." in name and not name.rsplit(".", 1)[1].isdigit() else name
    key: list[tuple[int, Decimal, str]] = []
    for number, part in enumerate(_NUMBER.split(stem)):
        if not part:
            continue
        if number % 2:  # re.split puts the captured numbers at odd positions
            key.append((0, Decimal(part), ""))
        else:
            key.append((1, Decimal(0), part.lower()))
    return tuple(key)


def check_order(order: str) -> str:
    if order not in SCAN_ORDERS:
        raise ValueError(f"order must be one of {', '.join(SCAN_ORDERS)}, got {order!r}")
    return order


def sort_scan_files(files: Iterable[Path], order: str = DEFAULT_ORDER) -> list[Path]:
    """``files`` in the given order (see the module docstring); ties fall back to the plain name."""
    check_order(order)
    paths = list(files)
    if order == "name":
        return sorted(paths, key=lambda p: p.name)
    if order == "mtime":
        return sorted(paths, key=lambda p: (p.stat().st_mtime_ns, natural_key(p.name), p.name))
    return sorted(paths, key=lambda p: (natural_key(p.name), p.name))
