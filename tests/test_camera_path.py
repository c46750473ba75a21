"""Camera paths: smooth, evenly paced interpolation of keyframes, the default trajectory path, JSON files."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from slam6d.camera_path import (
    CameraPath,
    Keyframe,
    camera_path_from_dict,
    load_camera_path,
    save_camera_path,
    trajectory_path,
)
from slam6d.errors import FormatError, Slam6dError
from slam6d.geometry import make_pose, rot_z, rotation_angle


def _positions(samples: list[tuple[np.ndarray, float]]) -> np.ndarray:
    return np.array([pose[:3, 3] for pose, _ in samples])


def _forward(samples: list[tuple[np.ndarray, float]]) -> np.ndarray:
    return np.array([pose[:3, 2] for pose, _ in samples])


def test_keyframe_pose_round_trip() -> None:
    pose = make_pose(rot_z(0.7) @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]]), [1.0, -2.0, 3.0])
    back = Keyframe.from_pose(pose, 45.0).pose()
    np.testing.assert_allclose(back, pose, atol=1e-12)
    with pytest.raises(ValueError, match="field of view"):
        Keyframe([0, 0, 0], [1, 0, 0, 0], fov_deg=200)


def test_frames_are_evenly_spaced_by_distance_despite_uneven_keyframes() -> None:
    xs = [0.0, 0.5, 4.0, 5.0, 12.0]
    path = CameraPath([Keyframe.looking_at([x, 0, 1], [x + 1, 0, 1]) for x in xs], speed=2.0)
    assert path.duration() == pytest.approx(6.0, rel=1e-3)  # 12 m at 2 m/s
    samples = path.sample(fps=10)
    assert len(samples) == path.frame_count(10) == 61
    positions = _positions(samples)
    np.testing.assert_allclose(positions[0], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(positions[-1], [12, 0, 1], atol=1e-9)
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.2, rtol=0.02)
    assert len(path.sample(frames=7)) == 7


def test_path_passes_through_keyframes_smoothly() -> None:
    corners = [[0, 0, 1], [5, 0, 1], [5, 5, 1], [10, 5, 1], [10, 10, 2]]
    path = CameraPath([Keyframe.looking_at(c, np.add(c, [1, 0, 0])) for c in corners])
    positions = _positions(path.sample(fps=30))
    for corner in corners:
        assert np.linalg.norm(positions - corner, axis=1).min() < 0.05
    steps = np.diff(positions, axis=0)
    turn = [
        math.degrees(math.acos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))
        for a, b in itertools.pairwise(steps)
    ]
    assert max(turn) < 5.0  # a spline, not a polyline with corners


def test_orientations_interpolate_and_turning_sets_the_pace() -> None:
    start = Keyframe.looking_at([0, 0, 0], [1, 0, 0], fov_deg=50.0)
    end = Keyframe.looking_at([0, 0, 0], [0, 1, 0], fov_deg=70.0)
    path = CameraPath([start, end], turn_speed_deg=30.0)
    assert path.duration() == pytest.approx(3.0, rel=1e-3)  # 90° at 30°/s, no motion
    samples = path.sample(frames=31)
    forward = _forward(samples)
    np.testing.assert_allclose(forward[0], [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(forward[-1], [0, 1, 0], atol=1e-9)
    np.testing.assert_allclose(forward[15], [math.sqrt(0.5), math.sqrt(0.5), 0], atol=1e-3)
    assert samples[15][1] == pytest.approx(60.0, abs=0.5)
    angles = [rotation_angle(a[:3, :3].T @ b[:3, :3]) for (a, _), (b, _) in itertools.pairwise(samples)]
    np.testing.assert_allclose(angles, math.radians(3.0), rtol=0.03)
    for pose, _ in samples:  # the horizon stays level: image x has no vertical component
        assert abs(pose[2, 0]) < 1e-6


def test_trajectory_path_follows_scans_one_metre_up_looking_ahead() -> None:
    # a stationary start (10 identical poses), then a quarter circle of radius 10 m
    angles = np.linspace(0.0, math.pi / 2, 40)
    poses = [make_pose(np.eye(3), [0.0, 0.0, 0.3])] * 10
    poses += [make_pose(rot_z(a), [10 * math.sin(a), 10 - 10 * math.cos(a), 0.3]) for a in angles]
    path = trajectory_path(poses, height=1.0, speed=2.0, look_ahead=3.0, pitch_deg=-10.0)
    arc = 10 * math.pi / 2
    assert path.duration() == pytest.approx(arc / 2.0, rel=0.01)  # the stationary start adds no time
    samples = path.sample(fps=25)
    positions = _positions(samples)
    np.testing.assert_allclose(positions[:, 2], 1.3, atol=1e-6)
    radius = np.linalg.norm(positions[:, :2] - [0.0, 10.0], axis=1)
    np.testing.assert_allclose(radius, 10.0, atol=0.05)
    forward = _forward(samples)
    pitch = np.degrees(np.arcsin(forward[:, 2]))
    np.testing.assert_allclose(pitch, -10.0, atol=0.5)
    # looking ahead: the view turns with the path and leads its tangent by the look-ahead chord
    tangent = np.gradient(positions[:, :2], axis=0)
    heading_view = np.arctan2(forward[:, 1], forward[:, 0])
    heading_path = np.arctan2(tangent[:, 1], tangent[:, 0])
    lead = np.degrees(heading_view - heading_path)[5:-40]
    np.testing.assert_allclose(lead, math.degrees(3.0 / 10.0 / 2.0), atol=1.5)


def test_single_scan_gets_a_look_around() -> None:
    pose = make_pose(rot_z(math.radians(30.0)), [1.0, 2.0, 0.0])
    samples = trajectory_path([pose]).sample(fps=10)
    positions = _positions(samples)
    np.testing.assert_allclose(positions, np.tile([1.0, 2.0, 1.0], (len(samples), 1)), atol=1e-9)
    headings = np.unwrap(np.arctan2(_forward(samples)[:, 1], _forward(samples)[:, 0]))
    assert math.degrees(headings[0]) == pytest.approx(30.0, abs=1e-6)
    assert math.degrees(headings[-1] - headings[0]) == pytest.approx(360.0, abs=1e-3)
    assert np.all(np.diff(headings) > 0)
    with pytest.raises(Slam6dError, match="no scan positions"):
        trajectory_path([])


def test_editing_keyframes() -> None:
    a, b, c = (Keyframe.looking_at([x, 0, 0], [x, 1, 0]) for x in (0.0, 1.0, 2.0))
    path = CameraPath()
    path.add(a)
    path.add(c)
    path.add(b, 1)
    assert [k.position[0] for k in path.keyframes] == [0, 1, 2]
    path.move(0, 2)
    assert [k.position[0] for k in path.keyframes] == [1, 2, 0]
    assert path.remove(1) is c
    assert len(path.preview(20)) == 20
    with pytest.raises(Slam6dError, match="no keyframes"):
        CameraPath().sample()


def test_json_round_trip(tmp_path: Path) -> None:
    path = trajectory_path([make_pose(np.eye(3), [x, 0.0, 0.0]) for x in range(6)], speed=1.5)
    file = save_camera_path(tmp_path / "path.json", path)
    loaded = load_camera_path(file)
    assert loaded.speed == 1.5 and loaded.look_ahead == path.look_ahead
    original, again = path.sample(frames=12), loaded.sample(frames=12)
    for (p0, f0), (p1, f1) in zip(original, again, strict=True):
        np.testing.assert_allclose(p1, p0, atol=1e-12)
        assert f0 == f1


def test_bad_path_files_name_the_problem(tmp_path: Path) -> None:
    broken = tmp_path / "broken.json"
    broken.write_text('{\n "keyframes": [\n  {"position": [0, 0, 0],,}\n ]\n}\n')
    with pytest.raises(FormatError) as info:
        load_camera_path(broken)
    assert info.value.path == broken and info.value.line == 3
    missing = tmp_path / "missing.json"
    missing.write_text(json.dumps({"keyframes": [{"position": [0, 0, 0], "orientation_wxyz": [1, 0, 0, 0]},
                                                 {"position": [1, 0, 0]}]}))  # fmt: skip
    with pytest.raises(FormatError, match=r"keyframes\[1\].orientation_wxyz: is missing"):
        load_camera_path(missing)
    with pytest.raises(FormatError, match="not a camera path"):
        camera_path_from_dict({"format": "something-else", "keyframes": []})
    with pytest.raises(FormatError, match="non-empty list"):
        camera_path_from_dict({"keyframes": []})
    with pytest.raises(FormatError, match="cannot read"):
        load_camera_path(tmp_path / "absent.json")
