"""Every reader fed mutated and truncated real files raises only the project's own errors.

A bounded sample of ``benchmarks/fuzz_readers.py`` (which runs 10,000 inputs per reader): any
exception other than a :class:`slam6d.errors.Slam6dError`, a refusal naming none of the files, any
input over the time limit and any allocation beyond the memory limit fails the test, with the
outcome and the input's number. The harness itself is tested with a reader that misbehaves on
request, so a sample that passes has really reached the readers.
"""

from __future__ import annotations

import tracemalloc
from collections import Counter
from pathlib import Path

import pytest
from misbehaving_reader import misbehave

from benchmarks.fuzz_readers import (
    Limits,
    Seed,
    Target,
    Worker,
    e57_page_checksums,
    fuzz,
    is_failure,
    mutated,
    read_outcome,
    targets,
)

INPUTS_PER_READER = 80
TARGETS = {t.name: t for t in targets()}


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_mutated_files_raise_only_the_projects_errors(name: str) -> None:
    failures: list[str] = []
    read: Counter[str] = Counter()

    def record(index: int, seed: Seed, outcome: str) -> None:
        read[seed.name] += 1
        if is_failure(outcome):
            failures.append(f"input {index}: {outcome} ({len(seed.data)} bytes, {seed.name})")

    counts = fuzz(TARGETS[name], INPUTS_PER_READER, record)
    assert sum(counts.values()) == INPUTS_PER_READER
    assert not failures, failures[:5]
    assert counts["ok"] < INPUTS_PER_READER, "no input was refused: the mutations did not reach the reader"


def test_the_same_number_makes_the_same_input_and_inputs_differ() -> None:
    target = TARGETS["ply"]
    assert mutated(target, 7) == mutated(target, 7)
    assert len({mutated(target, index).data for index in range(50)}) == 50
    assert all(mutated(target, index).data not in {s.data for s in target.seeds} for index in range(50))


def test_resealed_e57_pages_carry_the_checksums_libe57_writes() -> None:
    """The e57 inputs get past libE57's page checksums (else the fuzzer only tests the checksum)."""
    seed = TARGETS["e57"].seeds[0].data
    assert len(seed) >= 2048 and e57_page_checksums(seed) == seed
    damaged = bytearray(seed)
    damaged[1500] ^= 0x10
    resealed = e57_page_checksums(bytes(damaged))
    assert resealed[:1024] == seed[:1024] and resealed[2044:2048] != seed[2044:2048]


def test_the_harness_reports_every_kind_of_failure_and_goes_on(tmp_path: Path) -> None:
    """Each misbehaviour gets its outcome, and the worker is replaced after a hang or a death so
    the inputs after it are still read."""
    target = Target("misbehaving", [Seed("warm.txt", b"ok")], misbehave)
    worker = Worker(target, Limits(seconds=10.0), tmp_path)
    expected = {
        "ok": "ok",
        "refuse": "FormatError",
        "refuse anonymously": "UNNAMED FormatError: somewhere: not what this reader reads",
        "raise": "CRASH ValueError: a reader bug",
        "hang": "HANG",
        "allocate": "ALLOC",
        "abort": "CRASH the reading process died (signal SIGABRT)",
        "abort after a failed allocation": "ALLOC",
    }
    try:
        outcomes = {}
        for request in expected:
            outcomes[request] = worker.outcome(Seed("input.txt", request.encode()))
            assert worker.outcome(Seed("input.txt", b"ok")) == "ok"  # the next input is read
    finally:
        worker.close()
    assert outcomes == expected
    assert worker.restarts == 3  # the hang and the two aborts
    assert all(is_failure(outcomes[k]) for k in ("refuse anonymously", "raise", "hang", "allocate", "abort"))


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
    scan = TARGETS["ply"]  # read_scan: the suffix picks the format
    suffix = name.rsplit(".", 1)[-1]
    read_outcome(scan, Seed(f"warm.{suffix}", HUGE_HEADERS[name]), tmp_path)  # imports and compiles, untraced
    tracemalloc.start()
    try:
        outcome = read_outcome(scan, Seed(f"claim.{suffix}", HUGE_HEADERS[name]), tmp_path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert outcome == "FormatError", outcome
    assert peak < 16 << 20, f"{peak:,} bytes allocated"
