"""Reading folders as sequences: ordering, poses found beside the scans, --poses, and the map writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam6d.errors import FormatError
from slam6d.geometry import UOS, Y_UP, make_pose, pose_from_xyzrpy, quaternion_to_rotation, rotation_to_quaternion
from slam6d.io import read_scan, read_sequence
from slam6d.io.csv import write_csv_cloud
from slam6d.io.kitti import AmbiguousPosesWarning, write_kitti_bin
from slam6d.io.map import write_map
from slam6d.io.ply import write_ply
from slam6d.io.poses import write_kitti_poses, write_tum_poses
from slam6d.io.vtk import write_vtk

RNG = np.random.default_rng(11)
POSES = [pose_from_xyzrpy(float(i), 0.5 * i, 0.0, 0.0, 0.0, 0.1 * i) for i in range(4)]


def _kitti_folder(root: Path, count: int = 4) -> Path:
    bins = root / "velodyne"
    bins.mkdir(parents=True)
    for i in range(count):
        write_kitti_bin(bins / f"{i:06d}.bin", RNG.uniform(-5, 5, (30 + i, 3)), None)
    return bins


def test_kitti_poses_in_parent_found_from_either_folder(tmp_path: Path) -> None:
    bins = _kitti_folder(tmp_path)
    write_kitti_poses(tmp_path / "poses_subset.txt", POSES)
    write_kitti_poses(tmp_path / "poses_all.txt", POSES * 2)  # wrong line count: not a candidate
    (tmp_path / "times.txt").write_text("1\n2\n3\n4\n")  # right count, but not a poses file
    (tmp_path / "imu.csv").write_text("0.1,0.2,9.8\n")  # would read as a csv cloud: the bins must win
    for folder in (tmp_path, bins):
        seq = read_sequence(folder)
        assert seq.format_name == "kitti"
        assert [len(s) for s in seq] == [30, 31, 32, 33]  # name order
        assert all(s.has_pose for s in seq)
        np.testing.assert_allclose(seq[3].pose, POSES[3], atol=1e-8)


def test_kitti_ambiguous_poses_files_are_not_guessed(tmp_path: Path) -> None:
    bins = _kitti_folder(tmp_path)
    write_kitti_poses(tmp_path / "poses_a.txt", POSES)
    write_kitti_poses(bins / "poses_b.txt", POSES[::-1])
    with pytest.warns(AmbiguousPosesWarning, match="poses_a.txt"):
        seq = read_sequence(bins)
    assert not any(s.has_pose for s in seq)


def test_explicit_poses_file_overrides_and_is_sliced_with_first_last(tmp_path: Path) -> None:
    bins = _kitti_folder(tmp_path)
    write_kitti_poses(tmp_path / "poses.txt", POSES)
    override = tmp_path / "odometry.tum"
    shifted = [make_pose(p[:3, :3], p[:3, 3] + [0.0, 0.0, 1.0]) for p in POSES]
    write_tum_poses(override, shifted)
    seq = read_sequence(bins, first=1, last=2, poses_file=override)
    assert [s.name for s in seq] == ["000001", "000002"]
    np.testing.assert_allclose(seq[1].pose, shifted[2], atol=1e-7)


def test_too_few_poses_is_an_error(tmp_path: Path) -> None:
    bins = _kitti_folder(tmp_path)
    short = tmp_path / "short.txt"
    write_kitti_poses(short, POSES[:2])
    with pytest.raises(FormatError, match="2 poses for 4 scans"):
        read_sequence(bins, poses_file=short)


def _bunny_like(root: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Two y-up PLY scans and a .conf listing them in non-alphabetical order."""
    native = [RNG.uniform(-0.1, 0.1, (50, 3)), RNG.uniform(-0.1, 0.1, (60, 3))]
    write_ply(root / "zz_first.ply", native[0], binary=False)
    write_ply(root / "aa_second.ply", native[1])
    rotation = quaternion_to_rotation([0.9, 0.1, -0.3, 0.2])
    q = rotation_to_quaternion(rotation)  # (w, x, y, z)
    (root / "scene.conf").write_text(
        "camera 0 0 0 0 0 0 1\n"
        "bmesh zz_first.ply 0 0 0 0 0 0 1\n"
        f"bmesh aa_second.ply 0.01 -0.02 0.03 {q[1]} {q[2]} {q[3]} {q[0]}\n"
    )
    return native, [np.eye(4), make_pose(rotation.T, [0.01, -0.02, 0.03])]


def test_conf_sequence_order_poses_and_y_up(tmp_path: Path) -> None:
    native, native_poses = _bunny_like(tmp_path)
    for source in (tmp_path, tmp_path / "scene.conf"):
        seq = read_sequence(source)
        assert seq.format_name == "conf"
        assert [s.name for s in seq] == ["zz_first", "aa_second"]
        # y up in the file is z up in the canonical frame
        np.testing.assert_allclose(seq[1].points[:, 2], native[1][:, 1])
        np.testing.assert_allclose(seq[1].pose, Y_UP.pose_to_canonical(native_poses[1]), atol=1e-12)
        np.testing.assert_allclose(seq.native_poses()[1], native_poses[1], atol=1e-12)


def test_conf_errors_name_line_and_missing_files(tmp_path: Path) -> None:
    _bunny_like(tmp_path)
    conf = tmp_path / "scene.conf"
    conf.write_text(conf.read_text() + "bmesh third.ply 0 0 zero 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"scene.conf:4: not a number"):
        read_sequence(conf)
    conf.write_text("bmesh missing.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"missing\.ply"):
        read_sequence(tmp_path)


def test_pointmatcher_list_gives_order_and_ground_truth(tmp_path: Path) -> None:
    clouds = [RNG.uniform(-3, 3, (40, 3)) for _ in range(3)]
    for name, cloud in zip(("b.csv", "a.csv", "c.csv"), clouds, strict=True):
        write_csv_cloud(tmp_path / name, cloud)
    header = "reading, " + ", ".join(f"gT{r}{c}" for r in range(4) for c in range(4))
    rows = [f"{n}.csv, " + ", ".join(f"{v:.12g}" for v in p.reshape(16)) for n, p in zip("bac", POSES, strict=False)]
    (tmp_path / "list.csv").write_text("\n".join([header, *rows]) + "\n")
    seq = read_sequence(tmp_path, "csv")
    assert [s.name for s in seq] == ["b", "a", "c"]
    for scan, cloud, pose in zip(seq, clouds, POSES, strict=False):
        np.testing.assert_allclose(scan.points, cloud, atol=1e-7)
        np.testing.assert_allclose(scan.pose, pose, atol=1e-9)


def test_vtk_folder_follows_list_without_poses(tmp_path: Path) -> None:
    for i in (2, 0, 1):
        write_vtk(tmp_path / f"cloud.{i}.vtk", RNG.uniform(-1, 1, (10 + i, 3)))
    (tmp_path / "cloudList.csv").write_text("reading\ncloud.1.vtk\ncloud.0.vtk\ncloud.2.vtk\n")
    seq = read_sequence(tmp_path, "vtk")
    assert [len(s) for s in seq] == [11, 10, 12]
    assert not any(s.has_pose for s in seq)


@pytest.mark.parametrize("suffix", [".ply", ".laz", ".las"])
def test_map_writer_round_trip(tmp_path: Path, suffix: str) -> None:
    points = RNG.uniform(-100, 100, (500, 3)) + np.array([350000.0, 5800000.0, 40.0])  # UTM-sized coordinates
    colors = RNG.integers(0, 256, (500, 3)).astype(np.uint8)
    intensity = RNG.uniform(0, 1, 500)
    path = write_map(tmp_path / f"map{suffix}", points, colors=colors, intensity=intensity)
    scan = read_scan(path)
    np.testing.assert_allclose(scan.points, points, atol=1e-4)
    if suffix == ".ply":
        assert path.read_bytes().startswith(b"ply\nformat binary_little_endian")
        import open3d as o3d

        cloud = o3d.io.read_point_cloud(str(path))
        np.testing.assert_allclose(np.asarray(cloud.colors) * 255.0, colors, atol=1e-6)
    else:
        import laspy

        las = laspy.read(path)
        np.testing.assert_array_equal(np.asarray(las.red) // 257, colors[:, 0])


def test_map_writer_refuses_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"map\.obj"):
        write_map(tmp_path / "map.obj", np.zeros((3, 3)))


def test_uos_folder_reads_in_file_order_with_progress_and_stops_at_the_first_bad_file(tmp_path: Path) -> None:
    """Scans keep the numbering's order (scan010 after scan009), progress counts every file, and of
    two broken files the user is told about the first, by line."""
    from slam6d.io.uos import write_uos_scan

    clouds = [RNG.uniform(-500, 500, (300 + k, 3)) for k in range(12)]
    for k, cloud in enumerate(clouds):
        write_uos_scan(tmp_path, k, cloud, make_pose(np.eye(3), [k, 0.0, 0.0]))
    seen: list[tuple[int, int]] = []
    sequence = read_sequence(tmp_path, "uos", progress=lambda done, total: seen.append((done, total)))
    assert seen == [(k + 1, 12) for k in range(12)]
    assert [s.name for s in sequence] == [f"scan{k:03d}" for k in range(12)]
    for k, scan in enumerate(sequence):
        assert len(scan.points) == len(clouds[k])
        np.testing.assert_allclose(scan.pose[:3, 3], UOS.pose_to_canonical(make_pose(np.eye(3), [k, 0.0, 0.0]))[:3, 3])
    (tmp_path / "scan005.3d").write_text("1 2 3\n4 five 6\n")
    (tmp_path / "scan009.3d").write_text("1 2\n")
    with pytest.raises(FormatError, match=r"scan005\.3d:2: field \d+ is not a number"):
        read_sequence(tmp_path, "uos")
