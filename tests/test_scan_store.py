"""The on-demand scan store: float32 on disk, an LRU in memory that never holds more than its budget."""

from __future__ import annotations

import os
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from slam6d.geometry import make_pose
from slam6d.scan import Scan
from slam6d.scan_store import ScanStore, ScanStoreError, parse_bytes, store_sequence


def _scans(count: int, points: int, seed: int = 0) -> list[Scan]:
    rng = np.random.default_rng(seed)
    return [
        Scan(
            rng.normal(0, 20, (points + 7 * k, 3)),
            make_pose(np.eye(3), [k, 0.5 * k, 0.0]),
            name=f"scan{k:03d}",
            has_pose=k % 2 == 0,
        )
        for k in range(count)
    ]


def test_store_round_trips_points_as_float32_with_poses_and_names(tmp_path: Path) -> None:
    scans = _scans(5, 1000)
    store = ScanStore(ScanStore.create(tmp_path / "store", iter(scans)), budget=10**9)
    assert len(store) == 5
    for k, scan in enumerate(scans):
        np.testing.assert_array_equal(store.points(k), scan.points.astype(np.float32).astype(np.float64))
        np.testing.assert_array_equal(store.poses[k], scan.pose)
        assert store.names[k] == scan.name and store.has_pose[k] == scan.has_pose
        light = store.scan(k, with_points=False)
        assert len(light) == 0 and light.name == scan.name
    with pytest.raises(IndexError, match="scan 5"):
        store.points(5)


def test_prefixes_of_many_scans_are_their_first_points_in_one_pass(tmp_path: Path) -> None:
    scans = _scans(4, 500)
    store = ScanStore(ScanStore.create(tmp_path / "store", iter(scans)), budget=1)
    asked = [(2, 100), (0, 10_000), (3, 0), (1, 333), (2, 7)]  # any order; counts beyond a scan give all of it
    for (k, count), cloud in zip(asked, store.prefixes(asked), strict=True):
        assert cloud.dtype == np.float32 and cloud.flags.writeable
        np.testing.assert_array_equal(cloud, scans[k].points[:count].astype(np.float32))
    np.testing.assert_array_equal(store.prefix(1, 50), scans[1].points[:50].astype(np.float32))
    assert store.resident_bytes == 0  # prefixes are never cached
    with pytest.raises(IndexError, match="scan 4"):
        store.prefixes([(0, 1), (4, 1)])


def test_lru_never_holds_more_than_its_budget(tmp_path: Path) -> None:
    """By its own accounting after every request, and measured: numpy's allocations while 200
    random requests cycle through 12 scans stay within the budget plus the one read in flight."""
    scans = _scans(12, 20_000)
    directory = ScanStore.create(tmp_path / "store", iter(scans))
    one = 20_000 * 3 * 8
    budget = int(3.5 * one)
    store = ScanStore(directory, budget)
    rng = np.random.default_rng(1)
    tracemalloc.start()
    base, _ = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    for k in rng.integers(0, 12, 200):
        points = store.points(int(k))
        assert len(points) == len(scans[k])
        assert store.resident_bytes <= budget
        assert store.resident_bytes == sum(a.nbytes for a in store._resident.values())
        del points
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert store.peak_bytes <= budget
    assert 3 * one <= store.peak_bytes  # it does use the budget: three of these scans fit
    read_in_flight = 2 * (20_000 + 7 * 11) * 3 * 8  # the float32 read and its float64 copy, before eviction
    assert peak - base <= budget + read_in_flight, (peak - base, budget)
    assert store.loads < 200  # and hits the cache


def test_recently_used_scans_stay_and_the_oldest_go(tmp_path: Path) -> None:
    store = ScanStore(ScanStore.create(tmp_path / "store", iter(_scans(4, 1000))), budget=2 * 1100 * 24)
    store.points(0)
    store.points(1)
    store.points(0)  # 0 is now the most recent
    store.points(2)  # evicts 1
    assert list(store._resident) == [0, 2]
    loads = store.loads
    store.points(0)
    assert store.loads == loads


def test_a_scan_larger_than_the_budget_is_refused_by_name(tmp_path: Path) -> None:
    store = ScanStore(ScanStore.create(tmp_path / "store", iter(_scans(2, 1000))), budget=1000)
    with pytest.raises(ScanStoreError, match=r"scan 0 \(scan000\).*memory budget"):
        store.points(0)


def test_damaged_store_names_its_file(tmp_path: Path) -> None:
    directory = ScanStore.create(tmp_path / "store", iter(_scans(2, 100)))
    (directory / "points.f32").write_bytes(b"\0" * 12)
    with pytest.raises(ScanStoreError, match=r"points\.f32"):
        ScanStore(directory, 10**6)
    (directory / "index.json").write_text("{")
    with pytest.raises(ScanStoreError, match=r"index\.json"):
        ScanStore(directory, 10**6)


def test_store_sequence_reads_a_chunk_at_a_time(tmp_path: Path) -> None:
    scans = _scans(10, 50)
    asked: list[tuple[int, int]] = []

    def read_chunk(first: int, last: int) -> list[Scan]:
        asked.append((first, last))
        return scans[first : last + 1]

    store = ScanStore(store_sequence(tmp_path / "store", read_chunk, 10, chunk=4), 10**6)
    assert asked == [(0, 3), (4, 7), (8, 9)]
    np.testing.assert_array_equal(store.points(9), scans[9].points.astype(np.float32))


@pytest.mark.parametrize(
    ("text", "value"), [("2GB", 2 * 10**9), ("512MB", 512 * 10**6), ("1.5GiB", int(1.5 * 2**30)), ("1000", 1000)]
)
def test_memory_sizes_parse_as_written(text: str, value: int) -> None:
    assert parse_bytes(text) == value


@pytest.mark.parametrize("text", ["", "2XB", "-1GB", "0", "GB"])
def test_bad_memory_sizes_are_refused(text: str) -> None:
    with pytest.raises(ValueError, match="memory size"):
        parse_bytes(text)


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="VmHWM is Linux's")
def test_peak_memory_is_the_commands_own_not_its_launchers() -> None:
    """`slam6d run` / `slam6d render` started from a big process (a benchmark) report their own peak:
    Linux's ru_maxrss would carry the launcher's over fork and exec."""
    import subprocess
    import sys

    from slam6d.scan_store import peak_memory_bytes

    ballast = np.ones(300_000_000 // 8)  # touched: resident
    parent = peak_memory_bytes()
    child = subprocess.run(
        [sys.executable, "-c", "from slam6d.scan_store import peak_memory_bytes; print(peak_memory_bytes())"],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)},
    )
    assert parent >= ballast.nbytes
    assert 0 < int(child.stdout) < parent - 200_000_000
