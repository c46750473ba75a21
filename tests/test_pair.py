"""One pair from a poor start (``slam6d.pair``): when the octree search runs, and what comes back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam6d.errors import RegistrationError
from slam6d.geometry import invert, pose_difference, pose_from_xyzrpy, transform_points
from slam6d.icp import ICPConfig
from slam6d.pair import initial_transform, register_pair
from slam6d.scan import Scan
from slam6d.trace import read_trace, to_jsonable, write_trace
from tests.test_initial_guess import _hall

DEG = np.pi / 180


@pytest.fixture(scope="module")
def hall_scans() -> tuple[Scan, Scan, np.ndarray]:
    """Two scans of the synthetic hall with their true poses, and the true data->model transform."""
    rng = np.random.default_rng(5)
    model_pose = pose_from_xyzrpy(-3.0, 0.5, 1.3, 0.0, 0.0, 0.3)
    data_pose = pose_from_xyzrpy(-1.2, 0.0, 1.25, 0.01, -0.02, 0.55)
    model = Scan(transform_points(invert(model_pose), _hall(rng)), model_pose, "model", has_pose=True)
    data_points = transform_points(invert(data_pose), _hall(rng))
    data = Scan(data_points[np.linalg.norm(data_points, axis=1) < 15.0], data_pose, "data", has_pose=True)
    return model, data, invert(model_pose) @ data_pose


def _without_pose(scan: Scan, pose: np.ndarray) -> Scan:
    return Scan(scan.points, pose, scan.name, has_pose=False)


def test_start_comes_from_the_poses_only_when_both_scans_have_one(hall_scans) -> None:
    model, data, truth = hall_scans
    assert np.allclose(initial_transform(model, data), truth)
    assert np.allclose(initial_transform(model, _without_pose(data, data.pose)), np.eye(4))


def test_auto_skips_the_search_when_odometry_is_good(hall_scans) -> None:
    model, data, truth = hall_scans
    result = register_pair(model, data, "auto")
    assert result.guess is None and "octree_guess" not in result.seconds
    metres, radians = pose_difference(result.transform, truth)
    assert metres < 0.01 and radians < 0.1 * DEG


def test_auto_searches_without_poses_and_recovers_a_far_start(hall_scans) -> None:
    model, data, truth = hall_scans
    # Poses missing: the start is identity; put the data where a bad start would leave it.
    offset = pose_from_xyzrpy(0.7, -0.6, 0.15, 4 * DEG, -5 * DEG, 28 * DEG) @ truth
    far = Scan(data.points, np.eye(4), "data")  # has_pose=False
    plain = register_pair(model, far, "none", initial=offset)
    assert pose_difference(plain.transform, truth)[0] > 0.1  # ICP alone is lost from there
    guided = register_pair(model, far, "octree", initial=offset)
    assert guided.guess is not None and len(guided.guess.levels) >= 3
    metres, radians = pose_difference(guided.transform, truth)
    assert metres < 0.02 and radians < 0.3 * DEG


def test_result_and_traces_serialise(hall_scans, tmp_path: Path) -> None:
    model, data, _ = hall_scans
    result = register_pair(model, data, "octree", ICPConfig(max_iterations=5))
    write_trace(tmp_path / "t.json", result)
    trace = read_trace(tmp_path / "t.json")
    assert len(trace["icp"]["iterations"]) == len(result.icp.iterations) <= 5
    assert np.allclose(np.array(trace["transform"]), result.transform)
    levels = trace["guess"]["levels"]
    assert [lvl["cube_size"] for lvl in levels] == sorted((lvl["cube_size"] for lvl in levels), reverse=True)
    assert not (tmp_path / "t.json.tmp").exists()


def test_non_finite_values_become_null_in_json() -> None:
    assert to_jsonable({"a": np.array([1.0, np.nan]), "b": np.float32(np.inf), "c": Path("x")}) == {
        "a": [1.0, None],
        "b": None,
        "c": "x",
    }


def test_no_overlap_is_a_registration_error_naming_the_scans(hall_scans) -> None:
    model, data, _ = hall_scans
    far_away = Scan(data.points + 1000.0, data.pose, "lonely", has_pose=True)
    with pytest.raises(RegistrationError, match="lonely onto model"):
        register_pair(model, far_away, "none")


def test_unknown_guess_mode_is_refused(hall_scans) -> None:
    model, data, _ = hall_scans
    with pytest.raises(ValueError, match="guess must be one of"):
        register_pair(model, data, "sometimes")
