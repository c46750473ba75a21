"""Trajectory and pose-history files: KITTI, TUM, 4x4, g2o and 3DTK .frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam6d.errors import FormatError
from slam6d.geometry import UOS, pose_from_xyzrpy
from slam6d.io.frames import FrameType, final_frame_pose, read_frames, write_frames, write_sequence_frames
from slam6d.io.poses import (
    read_g2o,
    read_kitti_poses,
    read_poses_file,
    read_tum,
    write_g2o,
    write_kitti_poses,
    write_tum_poses,
)

RNG = np.random.default_rng(3)
POSES = [
    pose_from_xyzrpy(*RNG.uniform(-50, 50, 3), *RNG.uniform(-np.pi / 2 + 0.1, np.pi / 2 - 0.1, 3)) for _ in range(6)
]


def _assert_same_poses(actual: list[np.ndarray], expected: list[np.ndarray], metres: float, radians: float) -> None:
    """Element-wise (angles from arccos are too ill-conditioned near zero to test tight round trips)."""
    assert len(actual) == len(expected)
    for a, e in zip(actual, expected, strict=True):
        np.testing.assert_allclose(a[:3, 3], e[:3, 3], atol=metres)
        np.testing.assert_allclose(a[:3, :3], e[:3, :3], atol=radians)
        np.testing.assert_array_equal(a[3], [0.0, 0.0, 0.0, 1.0])


def test_kitti_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "poses.txt"
    write_kitti_poses(path, POSES)
    assert all(len(line.split()) == 12 for line in path.read_text().splitlines())
    _assert_same_poses(read_kitti_poses(path), POSES, 1e-7, 1e-8)


def test_tum_round_trip_with_and_without_timestamps(tmp_path: Path) -> None:
    path = tmp_path / "traj.tum"
    stamps = 1630577758.5 + np.arange(len(POSES)) * 0.1
    write_tum_poses(path, POSES, stamps)
    read_stamps, poses = read_tum(path)
    np.testing.assert_allclose(read_stamps, stamps, atol=1e-6)
    _assert_same_poses(poses, POSES, 1e-7, 1e-9)
    write_tum_poses(path, POSES)
    np.testing.assert_array_equal(read_tum(path)[0], np.arange(len(POSES)))
    qw = float(path.read_text().split()[7])  # order t x y z qx qy qz qw: qw last, non-negative
    assert 0.0 <= qw <= 1.0


def test_read_poses_file_accepts_kitti_tum_and_4x4(tmp_path: Path) -> None:
    kitti, tum, full = tmp_path / "k.txt", tmp_path / "t.txt", tmp_path / "f.txt"
    write_kitti_poses(kitti, POSES)
    write_tum_poses(tum, POSES)
    np.savetxt(full, np.array([p.reshape(16) for p in POSES]))
    for path in (kitti, tum, full):
        _assert_same_poses(read_poses_file(path), POSES, 1e-6, 1e-8)


@pytest.mark.parametrize(
    ("text", "line", "match"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1 x\n", 2, "field 12 is not a number"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n\n1 0 0 0 0 1 0 0 0 0 1\n", 3, "expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n# note\n2 0 0 0 0 1 0 0 0 0 1 0\n", 3, "not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n", 2, "NaN"),
    ],
)
def test_kitti_errors_name_file_and_line(tmp_path: Path, text: str, line: int, match: str) -> None:
    path = tmp_path / "poses.txt"
    path.write_text(text)
    with pytest.raises(FormatError, match=match) as info:
        read_kitti_poses(path)
    assert f"poses.txt:{line}:" in str(info.value)


def test_empty_poses_file_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "none.txt"
    path.write_text("")
    with pytest.raises(FormatError, match="no poses"):
        read_poses_file(path)


def test_g2o_round_trip(tmp_path: Path) -> None:
    from slam6d.geometry import invert

    info = np.diag([100.0, 100.0, 100.0, 400.0, 400.0, 400.0])
    info[0, 4] = info[4, 0] = 3.0  # off-diagonal entries survive the upper-triangle layout
    edges = [(i, i + 1, invert(POSES[i]) @ POSES[i + 1], info) for i in range(len(POSES) - 1)]
    edges.append((0, 5, invert(POSES[0]) @ POSES[5], np.eye(6)))
    path = tmp_path / "graph.g2o"
    write_g2o(path, POSES, edges)
    text = path.read_text()
    assert text.count("VERTEX_SE3:QUAT") == 6 and text.count("EDGE_SE3:QUAT") == 6 and "FIX 0" in text
    poses, read_edges = read_g2o(path)
    _assert_same_poses(poses, POSES, 1e-7, 1e-9)
    for (i, j, rel, inf), (ri, rj, rrel, rinf) in zip(edges, read_edges, strict=True):
        assert (i, j) == (ri, rj)
        _assert_same_poses([rrel], [rel], 1e-7, 1e-9)
        np.testing.assert_allclose(rinf, inf)


@pytest.mark.parametrize(
    ("line", "match"),
    [
        ("VERTEX_SE3:QUAT nan 1 0 0 0 0 0 1", "vertex ids must be integers"),  # found by the fuzzer: ValueError
        ("VERTEX_SE3:QUAT 1.5 1 0 0 0 0 0 1", "vertex ids must be integers"),
        ("VERTEX_SE3:QUAT 1 nan 0 0 0 0 0 1", "NaN or infinity"),
        ("VERTEX_SE3:QUAT 1 1 0 0 0 0 0 0", "quaternion has zero length"),
        ("EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 0 " + " ".join(["1"] * 21), "quaternion has zero length"),
        ("EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + " ".join(["inf"] * 21), "NaN or infinity"),
    ],
)
def test_g2o_errors_name_file_and_line(tmp_path: Path, line: str, match: str) -> None:
    path = tmp_path / "graph.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n" + line + "\n")
    with pytest.raises(FormatError, match=match) as info:
        read_g2o(path)
    assert "graph.g2o:2:" in str(info.value)


def test_tum_zero_quaternion_is_refused_not_turned_into_nan(tmp_path: Path) -> None:
    path = tmp_path / "tum.txt"
    path.write_text("0 0 0 0 0 0 0 1\n# comment\n1 1 0 0 0 0 0 0\n")
    with pytest.raises(FormatError, match=r"tum\.txt:3: quaternion has zero length"):
        read_poses_file(path)


def test_frames_round_trip_and_layout(tmp_path: Path) -> None:
    path = tmp_path / "scan000.frames"
    entries = [(POSES[0], FrameType.ICP), (POSES[1], FrameType.LUM), (POSES[2], FrameType.ELCH)]
    write_frames(path, entries)
    first = [float(v) for v in path.read_text().splitlines()[0].split()]
    assert len(first) == 17
    np.testing.assert_allclose(first[12:15], POSES[0][:3, 3], rtol=1e-8)  # column-major: translation 13-15
    assert first[16] == 1
    read = read_frames(path)
    assert [flag for _, flag in read] == [FrameType.ICP, FrameType.LUM, FrameType.ELCH]
    _assert_same_poses([p for p, _ in read], [p for p, _ in entries], 1e-6, 1e-8)
    _assert_same_poses([final_frame_pose(path)], [POSES[2]], 1e-6, 1e-8)


def test_frames_lines_keep_nine_significant_digits(tmp_path: Path) -> None:
    """3DTK's layout to the character: 16 column-major numbers with 9 significant digits, the flag."""
    pose = np.eye(4)
    pose[:3, 3] = [1 / 3, -1234567.891, 2.5e-12]
    path = tmp_path / "scan000.frames"
    write_frames(path, [(pose, FrameType.LUM)])
    assert path.read_text() == "1 0 0 0 0 1 0 0 0 0 1 0 0.333333333 -1234567.89 2.5e-12 1 3\n"


def test_sequence_frames_are_written_in_the_native_frame(tmp_path: Path) -> None:
    histories = [[(POSES[0], FrameType.ICP), (POSES[1], FrameType.LUM)], [(POSES[2], FrameType.ICP_INACTIVE)]]
    paths = write_sequence_frames(tmp_path, histories, UOS)
    assert [p.name for p in paths] == ["scan000.frames", "scan001.frames"]
    native = read_frames(paths[0])[1][0]
    np.testing.assert_allclose(native[:3, 3], UOS.pose_to_native(POSES[1])[:3, 3], rtol=1e-8)  # centimetres
    _assert_same_poses([UOS.pose_to_canonical(native)], [POSES[1]], 1e-6, 1e-8)


@pytest.mark.parametrize(
    ("line", "match"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0 5 6 7 1 9", "unknown frame type"),
        ("1 0 0 5 0 1 0 6 0 0 1 7 0 0 0 1 1", "column-major"),
        ("1 0 0 0 0 1 0 0 0 0 1 0 5 6 7 1", "expected 17 numbers"),
        ("1 0 0 0 0 1\r0 0 0 0 1 0 5 6 7 1 1", "expected 17 numbers"),  # \r ends a line (found by the fuzzer)
    ],
)
def test_frames_errors_name_line(tmp_path: Path, line: str, match: str) -> None:
    path = tmp_path / "scan001.frames"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 1\n" + line + "\n")
    with pytest.raises(FormatError, match=match) as info:
        read_frames(path)
    assert "scan001.frames:2:" in str(info.value)
