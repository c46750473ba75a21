"""Readers on the real datasets: counts, poses and frame conventions against the data's own references."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from slam6d.geometry import pose_from_xyzrpy, transform_points
from slam6d.io import read_scan, read_sequence
from slam6d.io.frames import FrameType, read_frames
from slam6d.io.poses import read_kitti_poses

pytestmark = pytest.mark.slow


def _median_gap(reference: np.ndarray, query: np.ndarray) -> float:
    distances, _ = KDTree(reference).query(query)
    return float(np.median(distances))


def test_kurt3d_counts_and_poses_match_3dtk(shared_data: Path) -> None:
    folder = shared_data / "kurt3d_3dtk"
    seq = read_sequence(folder)
    assert seq.format_name == "uos" and len(seq) == 3
    for index, scan in enumerate(seq):
        raw = np.loadtxt(folder / f"scan{index:03d}.3d")
        assert raw.shape == (81360, 3)
        no_echo = int((np.linalg.norm(raw, axis=1) >= 3276.0).sum())  # 3276.7 cm range = no return
        assert 0 < no_echo < 2000
        assert len(scan) == 81360 - no_echo
    # 3DTK's first frame is the odometry pose it read: ours, written back natively, must agree.
    for index, native in enumerate(seq.native_poses()):
        reference, flag = read_frames(folder / "slam6D_reference" / f"scan{index:03d}.frames")[0]
        assert isinstance(flag, FrameType)
        np.testing.assert_allclose(native[:3, 3], reference[:3, 3], atol=1e-4)  # cm
        np.testing.assert_allclose(native[:3, :3], reference[:3, :3], atol=1e-5)
    # The robot drives forward (uos z) about 1.6 m per scan: canonical x, metres.
    forward = [scan.pose[0, 3] for scan in seq]
    assert forward[1] == pytest.approx(1.569, abs=0.01) and forward[2] == pytest.approx(3.380, abs=0.01)
    assert abs(seq[1].pose[2, 3]) < 0.1  # uos y (up, -7.5 cm) became canonical z


def test_bunny_conf_aligns_the_views(shared_data: Path) -> None:
    seq = read_sequence(shared_data / "stanford_bunny" / "bun.conf")
    assert len(seq) == 10 and seq.format_name == "conf"
    assert [s.name for s in seq][:3] == ["bun000", "bun045", "bun090"]
    assert len(seq[0]) == 40256
    # [R(q)^T | t] brings neighbouring views together to well under a millimetre.
    assert _median_gap(seq[0].world_points(), seq[1].world_points()) < 0.001
    assert _median_gap(seq[0].world_points(), seq[7].world_points()) < 0.001  # bun315 closes the ring
    # y up in the file is z up here: the bunny stands about 15 cm tall along z.
    native = read_scan(shared_data / "stanford_bunny" / "bun000.ply", "ply").points
    np.testing.assert_allclose(seq[0].points[:, 2], native[:, 1])
    assert 0.12 < np.ptp(seq[0].points[:, 2]) < 0.2


@pytest.mark.parametrize("sub", ["", "velodyne_style_bin"])
def test_balm_hall_scans_with_poses(shared_data: Path, sub: str) -> None:
    folder = shared_data / "balm_hall"
    seq = read_sequence(folder / sub if sub else folder)
    assert seq.format_name == "kitti" and len(seq) == 89
    assert all(s.has_pose for s in seq)
    reference = read_kitti_poses(folder / "poses_subset_kitti3x4.txt")
    for scan, pose in zip(seq, reference, strict=True):
        np.testing.assert_array_equal(scan.pose, pose)
    sizes = [len(s) for s in seq]
    assert min(sizes) > 50_000 and max(sizes) < 100_000
    assert seq[0].intensity is not None and len(seq[0].intensity) == sizes[0]
    # The poses put consecutive scans on top of each other: nudging one by 10 cm or 1.7 degrees along
    # any axis loses overlap (fraction of points within 5 cm of the neighbour scan).
    a, b = seq[40], seq[41]
    tree = KDTree(a.world_points())

    def overlap(pose: np.ndarray) -> float:
        distances, _ = tree.query(transform_points(pose, b.points[::10]))
        return float(np.mean(distances < 0.05))

    at_reference = overlap(b.pose)
    for delta in np.vstack([np.eye(6)[:3] * 0.1, np.eye(6)[3:] * 0.03]):
        assert overlap(pose_from_xyzrpy(*delta) @ b.pose) < at_reference


def test_libpointmatcher_vtk_and_car_csv(shared_data: Path) -> None:
    folder = shared_data / "libpointmatcher_pairs"
    vtk = read_sequence(folder, "vtk")
    assert [s.name for s in vtk] == ["cloud.00000", "cloud.00001", "cloud.00002"]
    for scan in vtk:
        header = next(ln for ln in (folder / f"{scan.name}.vtk").read_text().splitlines() if ln.startswith("POINTS"))
        assert len(scan) == int(header.split()[1])
    cars = read_sequence(folder, "csv")
    assert [s.name for s in cars] == ["car_cloud400", "car_cloud401"]
    assert [len(s) for s in cars] == [24989, 25193]
    assert all(s.has_pose for s in cars)
    assert cars[1].pose[0, 1] == pytest.approx(0.169605) and cars[1].pose[1, 3] == pytest.approx(0.191433)
    # The list's gT is world_from_scan: applying it brings the pair much closer than leaving it.
    target = cars[0].world_points()
    aligned = _median_gap(target, cars[1].world_points())
    raw = _median_gap(target, transform_points(np.eye(4), cars[1].points))
    assert aligned < 0.15 < 0.4 < raw
