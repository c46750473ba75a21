"""Scan files of a folder are taken in acquisition order: natural by default, by name or time on request."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from slam6d.cli import app
from slam6d.errors import FormatError
from slam6d.io import read_sequence
from slam6d.io.kitti import write_kitti_bin
from slam6d.io.order import natural_key, sort_scan_files
from slam6d.io.pcd import write_pcd


def test_numbers_and_timestamps_sort_by_value() -> None:
    names = ["10.pcd", "2.pcd", "0.pcd", "1.pcd", "20.pcd", "3.pcd"]
    assert [p.name for p in sort_scan_files(map(Path, names))] == [
        "0.pcd",
        "1.pcd",
        "2.pcd",
        "3.pcd",
        "10.pcd",
        "20.pcd",
    ]
    stamps = ["1581234567.5.pcd", "1581234567.25.pcd", "1581234568.0.pcd", "1581234566.999.pcd"]
    assert [p.name for p in sort_scan_files(map(Path, stamps))] == [
        "1581234566.999.pcd",
        "1581234567.25.pcd",
        "1581234567.5.pcd",
        "1581234568.0.pcd",
    ]
    assert natural_key("scan_a9.ply") < natural_key("scan_a10.ply") < natural_key("scan_b1.ply")
    # plain text order is still available
    assert [p.name for p in sort_scan_files(map(Path, names), "name")][:3] == ["0.pcd", "1.pcd", "10.pcd"]


def _pcd_folder(root: Path, count: int) -> Path:
    """Scans whose point count tells the index they were written with (index + 10 points)."""
    root.mkdir()
    rng = np.random.default_rng(3)
    for i in range(count):
        write_pcd(root / f"{i}.pcd", rng.uniform(-5, 5, (10 + i, 3)))
    return root


def test_folder_of_unpadded_numbers_reads_in_natural_order(tmp_path: Path) -> None:
    folder = _pcd_folder(tmp_path / "scans", 12)
    sequence = read_sequence(folder)
    assert [scan.name for scan in sequence] == [str(i) for i in range(12)]
    assert [len(scan) for scan in sequence] == [10 + i for i in range(12)]
    by_name = read_sequence(folder, order="name")
    assert [scan.name for scan in by_name][:4] == ["0", "1", "10", "11"]


def test_mtime_order_follows_file_times(tmp_path: Path) -> None:
    folder = tmp_path / "bins"
    folder.mkdir()
    for rank, name in enumerate(["c.bin", "a.bin", "b.bin"]):
        write_kitti_bin(folder / name, np.random.default_rng(rank).uniform(-5, 5, (20, 3)), None)
        os.utime(folder / name, ns=(1_000_000_000 * (rank + 1), 1_000_000_000 * (rank + 1)))
    assert [scan.name for scan in read_sequence(folder, order="mtime")] == ["c", "a", "b"]
    assert [scan.name for scan in read_sequence(folder)] == ["a", "b", "c"]


def test_an_index_fixed_order_refuses_another(tmp_path: Path) -> None:
    from slam6d.io.uos import write_uos_scan

    for i in range(2):
        write_uos_scan(tmp_path, i, np.random.default_rng(i).uniform(-500, 500, (20, 3)), None)
    with pytest.raises(FormatError, match="scanNNN numbering"):
        read_sequence(tmp_path, order="mtime")
    with pytest.raises(ValueError, match="order must be one of"):
        read_sequence(tmp_path, order="random")


def test_run_takes_order_option(tmp_path: Path) -> None:
    folder = _pcd_folder(tmp_path / "scans", 3)
    result = CliRunner().invoke(app, ["run", str(folder), "--out", str(tmp_path / "out"), "--order", "sideways"])
    assert result.exit_code != 0
    assert "--order must be one of natural, name, mtime" in result.output
