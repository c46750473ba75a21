"""A binary copy of parsed scans, so that a session opens in a moment the second time.

Parsing text formats (uos, xyz, csv) is the slow part of opening a session; the cache holds the
parsed points (float32: ample in each scanner's own frame, sub-micrometre at 100 m, and half
the size) with their poses and names in one ``.npz``. It is valid while a fingerprint of how the
scans were read (format, frame, range filters) and of every source file's path, size and
modification time is unchanged; otherwise, or when the file is damaged, it is rebuilt.
"""

from __future__ import annotations

import hashlib
import os
import stat
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.geometry import FrameConvention
from slam6d.io.registry import ReadOptions, read_sequence
from slam6d.scan import Scan, ScanSequence

_VERSION = 1


class ScanCache:
    """The cache file of one set of sources, read the way given."""

    def __init__(
        self, path: Path, sources: Sequence[Path], format_name: str, convention: FrameConvention, options: ReadOptions
    ) -> None:
        self.path = path
        self.sources = list(sources)
        self.format_name = format_name
        self.convention = convention
        self.options = options

    def fingerprint(self) -> str:
        digest = hashlib.sha256(f"v{_VERSION}|{self.format_name}|{self.convention.name}".encode())
        digest.update(f"|{self.options.min_range}|{self.options.max_range}".encode())
        for src in self.sources:
            # one directory's entries sorted by name: the order of sorting the paths, without pathlib's
            # slow comparisons (0.2 s of a 1,000-scan folder's 4,000 files, on the path to a first view)
            for p in sorted(src.iterdir(), key=lambda entry: entry.name) if src.is_dir() else [src]:
                try:
                    st = p.stat()
                except OSError:
                    continue
                if stat.S_ISREG(st.st_mode):
                    digest.update(f"|{p}|{st.st_size}|{st.st_mtime_ns}".encode())
        return digest.hexdigest()

    def load(self, progress: Callable[[int, int], None] | None = None) -> ScanSequence:
        """The scans, from the cache when it is current, else parsed from the sources and cached."""
        fingerprint = self.fingerprint()
        if self.path.exists():
            try:
                with np.load(self.path, allow_pickle=False) as data:
                    if str(data["fingerprint"]) == fingerprint:
                        return self._from_arrays(data)
            except (OSError, ValueError, KeyError):
                pass  # a damaged cache is simply rebuilt
        scans = [
            scan
            for src in self.sources
            for scan in read_sequence(
                src, self.format_name, self.options, convention=self.convention, progress=progress
            ).scans
        ]
        sequence = ScanSequence(scans, self.convention, self.sources[0], self.format_name)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # written aside, then renamed: a crash leaves no half cache; named per thread, so two first opens
        # racing (the 3D view and a page's first request) do not rename each other's file away
        partial = self.path.with_suffix(f".{os.getpid()}-{threading.get_ident()}.tmp.npz")
        np.savez(partial, fingerprint=np.array(fingerprint), **_to_arrays(sequence))  # type: ignore[arg-type]
        partial.replace(self.path)
        # the points as every later open reads them back (float32): what a session computes must not
        # depend on whether its cache existed yet (relaxation moved scans ~0.1 mm apart otherwise)
        for scan in scans:
            scan.points = scan.points.astype(np.float32).astype(np.float64)
        return sequence

    def _from_arrays(self, data: Any) -> ScanSequence:
        counts = data["counts"]
        offsets = np.concatenate([[0], np.cumsum(counts)])
        points = data["points"]
        intensity = data["intensity"] if "intensity" in data.files else None
        scans = []
        for k in range(len(counts)):
            a, b = int(offsets[k]), int(offsets[k + 1])
            scans.append(
                Scan(
                    points[a:b].astype(np.float64),
                    data["poses"][k].copy(),
                    name=str(data["names"][k]),
                    source=Path(str(data["files"][k])) if str(data["files"][k]) else None,
                    intensity=None if intensity is None else intensity[a:b].copy(),
                    has_pose=bool(data["has_pose"][k]),
                )
            )
        return ScanSequence(scans, self.convention, None, self.format_name)


def _to_arrays(sequence: ScanSequence) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {
        "counts": np.array([len(s) for s in sequence.scans], dtype=np.int64),
        "points": np.concatenate([s.points for s in sequence.scans]).astype(np.float32),
        "poses": np.stack([s.pose for s in sequence.scans]),
        "has_pose": np.array([s.has_pose for s in sequence.scans]),
        "names": np.array([s.name for s in sequence.scans]),
        "files": np.array([str(s.source or "") for s in sequence.scans]),
    }
    if all(s.intensity is not None for s in sequence.scans):
        arrays["intensity"] = np.concatenate([s.intensity for s in sequence.scans if s.intensity is not None])
    return arrays
