"""Scans kept on disk and loaded on demand: memory bounded by a budget, not by the session's size.

A thousand scans of 100,000 points are 2.4 GB as float64 clouds; the stages after reading need
only each scan's reduced copy (one point per voxel), its kd-tree and normals. A :class:`ScanStore`
writes every scan's points once, as float32 in the scanner's own frame (sub-micrometre at 100 m,
half the size), to one flat file beside an index of counts, poses and names, and hands a scan
back as float64 when a stage asks for it. The clouds asked for recently stay in memory in a
least-recently-used cache bounded by ``budget`` bytes, accounted by the arrays' own sizes
(:attr:`ScanStore.resident_bytes`, :attr:`ScanStore.peak_bytes`); reading a scan uses ordinary
file reads, not a memory map, so pages of the file never count as the process's memory.

:func:`store_sequence` fills a store from any readable source a chunk of scans at a time, so not
even reading holds the whole session. :func:`parse_bytes` reads budgets as a user writes them
(``2GB``, ``512MB``, ``1.5G``).
"""

from __future__ import annotations

import json
import os
import re
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Slam6dError
from slam6d.geometry import CANONICAL, CONVENTIONS, FrameConvention, Matrix
from slam6d.io.order import DEFAULT_ORDER
from slam6d.io.registry import ReadOptions, list_scan_files, read_sequence, resolve_format
from slam6d.scan import Scan, ScanSequence

FloatArray = NDArray[np.float64]

POINTS_FILE = "points.f32"
INDEX_FILE = "index.json"
_UNITS = {"": 1, "B": 1, "K": 10**3, "KB": 10**3, "M": 10**6, "MB": 10**6, "G": 10**9, "GB": 10**9, "T": 10**12}
_INDEX_KEYS = ("counts", "poses", "has_pose", "names", "convention")
_UNITS |= {"KIB": 2**10, "MIB": 2**20, "GIB": 2**30, "TB": 10**12}

__all__ = ["ScanStore", "ScanStoreError", "parse_bytes", "peak_memory_bytes", "store_sequence", "store_source"]


class ScanStoreError(Slam6dError):
    """A store that cannot be read, or a budget that cannot hold what is asked of it."""


def parse_bytes(text: str) -> int:
    """``"2GB"`` -> 2,000,000,000; decimal units (KB, MB, GB, TB), binary ones as KiB, MiB, GiB."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([A-Za-z]*)\s*", text)
    unit = match.group(2).upper() if match else ""
    if match is None or unit not in _UNITS:
        raise ValueError(f"not a memory size: {text!r} (write e.g. 2GB, 512MB or 1.5GiB)")
    value = int(float(match.group(1)) * _UNITS[unit])
    if value <= 0:
        raise ValueError(f"a memory size must be positive, got {text!r}")
    return value


def peak_memory_bytes() -> int:
    """The process's peak resident memory so far.

    On Linux from ``/proc/self/status``'s ``VmHWM``: ``ru_maxrss`` also keeps the peak of the
    process that started this one (Linux carries the parent's high-water mark across fork and
    exec), so a command launched from a big benchmark process reported the benchmark's memory.
    Elsewhere ``ru_maxrss`` (macOS reports bytes, others kilobytes).
    """
    import resource
    import sys

    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # "VmHWM:   452168 kB"
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


class ScanStore:
    """The scans of one directory written by :meth:`create` / :func:`store_sequence`; see the module docstring."""

    def __init__(self, directory: Path | str, budget: int) -> None:
        self.directory = Path(directory)
        self.budget = int(budget)
        if self.budget <= 0:
            raise ValueError(f"the memory budget must be positive, got {budget}")
        index_path = self.directory / INDEX_FILE
        try:
            index = json.loads(index_path.read_text())
            self.counts = np.array(index["counts"], dtype=np.int64)
            self.poses: list[Matrix] = [np.array(p, dtype=np.float64).reshape(4, 4) for p in index["poses"]]
            self.has_pose: list[bool] = [bool(h) for h in index["has_pose"]]
            self.names: list[str] = [str(n) for n in index["names"]]
            self.convention = CONVENTIONS[index.get("convention", CANONICAL.name)]
            self.extra: dict[str, Any] = {k: v for k, v in index.items() if k not in _INDEX_KEYS}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ScanStoreError(f"{index_path}: not a readable scan store index ({exc})") from exc
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])
        expected = int(self.offsets[-1]) * 3 * 4
        points_path = self.directory / POINTS_FILE
        if not points_path.is_file() or points_path.stat().st_size != expected:
            raise ScanStoreError(f"{points_path}: missing or not {expected} bytes as its index says")
        self._resident: OrderedDict[int, FloatArray] = OrderedDict()
        self.resident_bytes = 0
        self.peak_bytes = 0
        self.loads = 0  # reads from disk (misses of the cache)
        self.read_bytes = 0  # bytes of points read from disk, by points() and prefix() alike
        self._lock = threading.Lock()  # the pipeline reduces scans on two threads

    def __len__(self) -> int:
        return len(self.counts)

    @staticmethod
    def create(
        directory: Path | str,
        scans: Iterable[Scan],
        convention: FrameConvention = CANONICAL,
        extra: dict[str, Any] | None = None,
    ) -> Path:
        """Write ``scans`` (consumed one at a time, so an iterator holds one scan at once) as a store;
        ``convention`` is the frame of the source they were read from (poses written back use it).
        ``extra`` goes into the index as well (what a store built for one purpose records about
        itself, e.g. :mod:`slam6d.scan_levels`' fingerprint); read it back as :attr:`extra`."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        counts, poses, has_pose, names = [], [], [], []
        with open(out / POINTS_FILE, "wb") as stream:
            for scan in scans:
                np.ascontiguousarray(scan.points, dtype=np.float32).tofile(stream)
                counts.append(len(scan))
                poses.append(np.asarray(scan.pose, dtype=np.float64).ravel().tolist())
                has_pose.append(bool(scan.has_pose))
                names.append(scan.name)
        index = {
            "counts": counts,
            "poses": poses,
            "has_pose": has_pose,
            "names": names,
            "convention": convention.name,
            **(extra or {}),
        }
        (out / INDEX_FILE).write_text(json.dumps(index))
        return out

    def points(self, k: int) -> FloatArray:
        """Scan k's points (float64, own frame): from memory when used recently, else read from disk.

        The caller must not modify the array: it is shared with later callers while it stays cached.
        """
        if not 0 <= k < len(self.counts):
            raise IndexError(f"scan {k} is not in the store of {len(self.counts)} scans at {self.directory}")
        with self._lock:
            return self._points(k)

    def _points(self, k: int) -> FloatArray:
        cached = self._resident.get(k)
        if cached is not None:
            self._resident.move_to_end(k)
            return cached
        size = int(self.counts[k]) * 3 * 8
        if size > self.budget:
            raise ScanStoreError(
                f"scan {k} ({self.names[k]}) needs {size / 1e6:.1f} MB, more than the whole memory budget"
                f" of {self.budget / 1e6:.1f} MB"
            )
        while self._resident and self.resident_bytes + size > self.budget:
            _, evicted = self._resident.popitem(last=False)
            self.resident_bytes -= evicted.nbytes
        start, count = int(self.offsets[k]), int(self.counts[k])
        raw = np.fromfile(self.directory / POINTS_FILE, dtype=np.float32, count=count * 3, offset=start * 12)
        points = raw.reshape(-1, 3).astype(np.float64)
        points.flags.writeable = False
        self._resident[k] = points
        self.resident_bytes += points.nbytes
        self.peak_bytes = max(self.peak_bytes, self.resident_bytes)
        self.loads += 1
        self.read_bytes += raw.nbytes
        return points

    def prefix(self, k: int, count: int) -> NDArray[np.float32]:
        """The first ``count`` points of scan k as stored (float32), read from disk and not cached: the
        levels of detail of :mod:`slam6d.scan_levels` are prefixes, read far more often than once."""
        return self.prefixes([(k, count)])[0]

    def prefixes(self, requests: Iterable[tuple[int, int]]) -> list[NDArray[np.float32]]:
        """:meth:`prefix` for each ``(scan, count)``, with one open of the points file for all of them.

        A view reads a prefix of every scan of a 1,000-scan map at once; opening the file per scan cost
        ~0.35 ms each (0.35 s on the path to the first view), the reads themselves a few µs.
        """
        path = self.directory / POINTS_FILE
        clouds = []
        fd = os.open(path, os.O_RDONLY)
        try:
            for k, count in requests:
                if not 0 <= k < len(self.counts):
                    raise IndexError(f"scan {k} is not in the store of {len(self.counts)} scans at {self.directory}")
                points = np.empty((min(max(int(count), 0), int(self.counts[k])), 3), dtype=np.float32)
                buffer = points.data.cast("B") if len(points) else memoryview(b"")  # (no cast of an empty shape)
                offset, done = int(self.offsets[k]) * 12, 0
                while done < len(buffer):  # a read may return less than asked for
                    read = os.preadv(fd, [buffer[done:]], offset + done)
                    if read == 0:
                        raise ScanStoreError(f"{path}: ends inside scan {k} ({self.names[k]})")
                    done += read
                clouds.append(points)
        finally:
            os.close(fd)
        with self._lock:
            self.read_bytes += sum(cloud.nbytes for cloud in clouds)
        return clouds

    @staticmethod
    def holds(directory: Path | str) -> bool:
        """Whether ``directory`` is a store (e.g. the ``scan_store`` folder ``slam6d run --memory-budget`` writes)."""
        return (Path(directory) / INDEX_FILE).is_file() and (Path(directory) / POINTS_FILE).is_file()

    def scan(self, k: int, with_points: bool = True) -> Scan:
        """Scan k with its pose and name; without points (an empty cloud) when only those are needed."""
        points = self.points(k) if with_points else np.empty((0, 3))
        return Scan(points, self.poses[k].copy(), name=self.names[k], has_pose=self.has_pose[k])


def store_sequence(
    directory: Path | str,
    read_chunk: Callable[[int, int], list[Scan]],
    count: int,
    chunk: int = 32,
    progress: Callable[[int, int], None] | None = None,
    convention: FrameConvention = CANONICAL,
) -> Path:
    """Fill a store at ``directory`` with ``count`` scans, ``read_chunk(first, last)`` giving scans
    first..last (inclusive) at a time: at most ``chunk`` full clouds are in memory while reading."""

    def scans() -> Iterable[Scan]:
        for first in range(0, count, chunk):
            last = min(count, first + chunk) - 1
            yield from read_chunk(first, last)
            if progress is not None:
                progress(last + 1, count)

    return ScanStore.create(directory, scans(), convention)


def store_source(
    directory: Path | str,
    source: Path,
    format_name: str | None,
    options: ReadOptions,
    budget: int,
    first: int = 0,
    last: int | None = None,
    poses_file: Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    order: str = DEFAULT_ORDER,
) -> tuple[ScanSequence, ScanStore]:
    """Read scans first..last of ``source`` into a store at ``directory`` a chunk at a time, to be
    kept in memory within ``budget`` bytes.

    Returns the sequence (poses and names only: its scans' clouds are empty) and the store with
    the points. Poses from ``poses_file`` or the format's sequence poses apply as in
    :func:`slam6d.io.registry.read_sequence`, which reads each chunk.
    """
    fmt = resolve_format(source, format_name)
    listing = source.is_dir() or source.suffix.lower() in fmt.index_suffixes
    total = len(list_scan_files(source, fmt, order) if listing else [source])
    stop = total if last is None else min(total, last + 1)
    count = max(0, stop - first)
    if count == 0:
        raise ScanStoreError(f"{source}: no scans between --first {first} and --last {last}")
    read: list[ScanSequence] = []

    def read_chunk(a: int, b: int) -> list[Scan]:
        sequence = read_sequence(source, fmt.name, options, first + a, first + b, poses_file, order=order)
        read[:] = [sequence]
        return sequence.scans

    store_sequence(directory, read_chunk, count, progress=progress, convention=fmt.convention)
    store = ScanStore(directory, budget)
    template = read[0]
    scans = [store.scan(k, with_points=False) for k in range(len(store))]
    return ScanSequence(scans, template.convention, source, template.format_name), store
