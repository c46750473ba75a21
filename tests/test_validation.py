"""Values from outside the engine: rigid poses, unit quaternions, bounded points; refused, never stored."""

from __future__ import annotations

import numpy as np
import pytest

from slam6d.camera_path import keyframe_from_dict
from slam6d.errors import InvalidValueError
from slam6d.geometry import check_point, check_quaternion, check_rigid, euler_to_rotation, make_pose
from slam6d.session import Session
from tests.session_fixtures import write_corridor_scans


def _rigid() -> np.ndarray:
    return make_pose(euler_to_rotation(0.3, -0.2, 1.1), [1.0, 2.0, -3.0])


NOT_RIGID = {
    "zero": (np.zeros((4, 4)), "bottom row"),
    "scaled": (np.diag([3.0, 3.0, 3.0, 1.0]), "within \\[-1, 1\\]"),
    "slightly scaled": (np.diag([1.01, 1.01, 1.01, 1.0]), "not orthonormal"),
    "sheared": (make_pose(np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), [0, 0, 0]), "not orthonormal"),
    "reflection": (np.diag([1.0, 1.0, -1.0, 1.0]), "determinant"),
    "garbage bottom row": (np.vstack([_rigid()[:3], [5.0, 0.0, 0.0, 1.0]]), "bottom row"),
    "huge translation": (make_pose(np.eye(3), [1e308, 0, 0]), "beyond"),
    "nan": (np.full((4, 4), np.nan), "finite"),
}


@pytest.mark.parametrize("kind", sorted(NOT_RIGID))
def test_check_rigid_refuses_what_is_not_a_pose_and_names_the_field(kind: str) -> None:
    matrix, reason = NOT_RIGID[kind]
    with pytest.raises(InvalidValueError, match=f"^poses\\[2\\]: .*{reason}") as info:
        check_rigid(matrix, "poses[2]")
    assert info.value.field == "poses[2]"


def test_check_rigid_accepts_rotations_rounded_as_text_files_store_them() -> None:
    pose = _rigid()
    rounded = np.round(pose, 6)
    np.testing.assert_allclose(check_rigid(rounded), rounded)
    with pytest.raises(InvalidValueError, match="4x4"):
        check_rigid([[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # ragged
    with pytest.raises(InvalidValueError, match="4x4"):
        check_rigid(np.eye(3))


def test_quaternions_are_normalised_or_refused() -> None:
    np.testing.assert_allclose(check_quaternion([2.0, 0.0, 0.0, 0.0]), [1.0, 0.0, 0.0, 0.0])
    for bad, reason in (([1e200, 0, 0, 0], "within"), ([0, 0, 0, 0], "zero"), ([np.nan, 0, 0, 1], "finite")):
        with pytest.raises(InvalidValueError, match=reason):
            check_quaternion(bad, "keyframes[0].orientation_wxyz")
    with pytest.raises(InvalidValueError, match="4 numbers"):
        check_quaternion([1, 0, 0])
    with pytest.raises(InvalidValueError, match="beyond"):
        check_point([0, 0, 1e9])


def test_keyframe_fields_are_named_and_bools_are_not_numbers() -> None:
    with pytest.raises(InvalidValueError, match=r"^keyframes\[3\]\.orientation_wxyz: "):
        keyframe_from_dict({"position": [0, 0, 0], "orientation_wxyz": [1e200, 0, 0, 0]}, "keyframes[3]")
    with pytest.raises(InvalidValueError, match=r"^k\.fov_deg: must be a number"):
        keyframe_from_dict({"position": [0, 0, 0], "orientation_wxyz": [1, 0, 0, 0], "fov_deg": False}, "k")


@pytest.fixture
def session(tmp_path):
    write_corridor_scans(tmp_path / "s" / "scans", scans=3, points=300)
    made = Session.create(tmp_path / "s", "validation", "scans")
    made.load_sequence()
    return made


@pytest.mark.parametrize("kind", sorted(NOT_RIGID))
def test_the_journal_never_stores_a_pose_that_is_not_rigid(session, kind: str) -> None:
    poses = session.poses()
    poses[1] = NOT_RIGID[kind][0]
    entries = len(session.journal.entries())
    with pytest.raises(InvalidValueError, match=r"^poses\[1\]: "):
        session.journal.commit(poses, "ana", "move")
    assert session.journal.revisions() == [0] and len(session.journal.entries()) == entries


def test_a_poisoned_keyframe_is_refused_and_an_old_one_never_wedges_the_path(session) -> None:
    good = {"position": [0.0, 0.0, 1.0], "orientation_wxyz": [2.0, 0.0, 0.0, 0.0], "fov_deg": 50}
    stored = session.set_camera_path([good], "ana")
    assert stored[0]["orientation_wxyz"] == [1.0, 0.0, 0.0, 0.0]
    with pytest.raises(InvalidValueError, match=r"keyframes\[1\]\.orientation_wxyz"):
        session.set_camera_path([good, {**good, "orientation_wxyz": [1e200, 0, 0, 0]}], "ana")
    assert session.camera_path() == stored  # the refused list was not stored
    # a path stored before keyframes were checked: the bad keyframe is left out and named
    session.journal.append("old", "camera_path", {"keyframes": [good, {**good, "orientation_wxyz": [0, 0, 0, 0]}]})
    assert len(session.camera_path()) == 1
    assert session.camera_path_problems() == [
        "keyframes[1].orientation_wxyz: is zero (or nearly): it names no rotation"
    ]
    session.set_camera_path([], "ana")  # a path can always be cleared
    assert session.camera_path() == [] and session.camera_path_problems() == []


def test_readers_refuse_what_is_not_a_regular_file_before_reading(tmp_path) -> None:
    """A FIFO would block the reading thread forever, /dev/zero never ends: both refused at once."""
    import os

    from slam6d.errors import FormatError
    from slam6d.io.registry import read_scan

    fifo = tmp_path / "scan000.3d"
    os.mkfifo(fifo)
    with pytest.raises(FormatError, match="not a regular file \\(a FIFO\\)"):
        read_scan(fifo, "uos")
    with pytest.raises(FormatError, match="not a regular file \\(a device\\)"):
        read_scan("/dev/zero", "xyz")
    (tmp_path / "folder.ply").mkdir()
    with pytest.raises(FormatError, match="not a regular file \\(a folder\\)"):
        read_scan(tmp_path / "folder.ply", "ply")


def test_errors_never_quote_the_content_of_the_file(tmp_path) -> None:
    """A secret-looking first line must not come back in the message, whatever format is claimed."""
    from slam6d.errors import Slam6dError
    from slam6d.io.registry import read_scan

    secret = "root:x:0:0:SECRET-TOKEN:/root:/bin/bash\nbin:x:1:1::/bin:/usr/sbin/nologin\n"
    for suffix, fmt in (
        (".csv", "csv"),
        (".xyz", "xyz"),
        (".3d", "uos"),
        (".ply", "ply"),
        (".pcd", "pcd"),
        (".vtk", "vtk"),
    ):
        path = tmp_path / f"passwd{suffix}"
        path.write_text(secret)
        with pytest.raises(Slam6dError) as info:
            read_scan(path, fmt)
        message = str(info.value)
        assert "SECRET" not in message and "root:x" not in message and "nologin" not in message, message


def test_a_pose_carried_by_a_file_must_be_rigid(tmp_path) -> None:
    from slam6d.errors import FormatError
    from slam6d.io.pcd import write_pcd
    from slam6d.io.registry import read_scan

    path = tmp_path / "scaled.pcd"
    write_pcd(path, np.random.default_rng(0).uniform(-1, 1, (20, 3)))
    raw = path.read_bytes().replace(b"VIEWPOINT 0 0 0 1 0 0 0", b"VIEWPOINT 0 0 1e300 1 0 0 0")
    path.write_bytes(raw)
    with pytest.raises(FormatError, match=r"scaled\.pcd: pose: translation"):
        read_scan(path)


def test_a_scan_folder_never_lists_links_leading_out_of_it(tmp_path) -> None:
    from slam6d.io.registry import get_format, list_scan_files

    write_corridor_scans(tmp_path / "scans", scans=2, points=50)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret.3d").write_text("1 2 3\n")
    (tmp_path / "scans" / "scan002.3d").symlink_to(outside / "secret.3d")
    (tmp_path / "scans" / "scan002.pose").write_text("0 0 0\n0 0 0\n")
    listed = list_scan_files(tmp_path / "scans", get_format("uos"))
    assert [p.name for p in listed] == ["scan000.3d", "scan001.3d"]
