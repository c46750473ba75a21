"""Every reader fed mutated and truncated real files raises only the project's own errors.

A bounded sample of ``benchmarks/fuzz_readers.py`` (which runs 10,000 inputs per reader): any
exception other than a :class:`slam6d.errors.Slam6dError`, any input over the time limit and any
allocation beyond the memory limit fails the test, with the outcome and the input's size.
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import pytest

from benchmarks.fuzz_readers import Seed, fuzz, is_failure, outcome_of, targets

INPUTS_PER_READER = 80
TARGETS = {t.name: t for t in targets()}


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_mutated_files_raise_only_the_projects_errors(name: str) -> None:
    failures: list[str] = []

    def record(seed: Seed, outcome: str) -> None:
        if is_failure(outcome):
            failures.append(f"{outcome} ({len(seed.data)} bytes, {seed.name})")

    counts = fuzz(TARGETS[name], INPUTS_PER_READER, record)
    assert sum(counts.values()) == INPUTS_PER_READER
    assert not failures, failures[:5]
    assert counts["ok"] + sum(v for k, v in counts.items() if k != "ok") == INPUTS_PER_READER


HUGE_HEADERS = {
    "ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n" + bytes(120)),
    "ascii.ply": (b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n1 2 3\n"),
    "pcd": (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000000000\nHEIGHT 1\n"
            b"POINTS 1000000000000\nDATA binary\n" + bytes(120)),
    "ascii.pcd": (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000000000\nHEIGHT 1\n"
                  b"POINTS 1000000000000\nDATA ascii\n1 2 3\n"),
    "compressed.pcd": (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 357913941\nHEIGHT 1\n"
                       b"POINTS 357913941\nDATA binary_compressed\n" + b"\x04\x00\x00\x00\xfc\xff\xff\xff" + bytes(8)),
    "vtk": b"# vtk DataFile Version 3.0\nx\nBINARY\nDATASET POLYDATA\nPOINTS 1000000000000 float\n" + bytes(120),
    "ascii.vtk": b"# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 1000000000000 float\n1 2 3\n",
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(HUGE_HEADERS))
def test_a_header_claiming_a_trillion_points_is_refused_without_allocating(name: str, tmp_path: Path) -> None:
    scan = next(t for t in TARGETS.values() if t.name == "ply")  # read_scan: the suffix picks the format
    suffix = name.rsplit(".", 1)[-1]
    outcome_of(scan, Seed(f"warm.{suffix}", HUGE_HEADERS[name]), tmp_path)  # imports and compiles, untraced
    tracemalloc.start()
    try:
        outcome = outcome_of(scan, Seed(f"claim.{suffix}", HUGE_HEADERS[name]), tmp_path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert outcome == "FormatError", outcome
    assert peak < 16 << 20, f"{peak:,} bytes allocated"
