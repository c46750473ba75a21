"""The simulator writes sessions whose ground truth is consistent, whose odometry drifts, and which reproduce."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from slam6d.cli import app
from slam6d.errors import Slam6dError
from slam6d.geometry import UOS, pose_difference, transform_points, xyzrpy_from_pose
from slam6d.io import read_sequence
from slam6d.io.poses import read_kitti_poses
from slam6d.metrics import absolute_trajectory_error, relative_pose_error
from slam6d.simulate import SimulatedSession, SimulationConfig, build_scene, simulate_session

SMALL = SimulationConfig(seed=7, scans=12, points_per_scan=16_000)


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> SimulatedSession:
    return simulate_session(tmp_path_factory.mktemp("sim") / "session", SMALL)


def session_files(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def point_to_plane_median(a_world: np.ndarray, b_world: np.ndarray) -> float:
    """Median distance of b's points to planes fitted to a's neighbourhoods (clearly planar spots only).

    Point-to-point distances between two scans are dominated by how sparsely each samples a
    surface; distances to the local surface measure registration error instead.
    """
    dist, idx = cKDTree(a_world).query(b_world, k=10)
    near = dist[:, -1] < 1.0
    neighbours = a_world[idx[near]]
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    eigenvalues, eigenvectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    # Flat, and not a single scan line (whose 'normal' would be arbitrary).
    planar = (eigenvalues[:, 0] < 0.003 * eigenvalues[:, 1]) & (eigenvalues[:, 1] > 0.05 * eigenvalues[:, 2])
    assert planar.sum() > 300, "too little overlap to judge"
    offsets = b_world[near][planar] - neighbours[planar].mean(axis=1)
    return float(np.median(np.abs(np.einsum("ni,ni->n", offsets, eigenvectors[planar, :, 0]))))


def test_same_seed_writes_identical_files_and_another_seed_does_not(tmp_path: Path) -> None:
    config = SimulationConfig(seed=11, scans=4, points_per_scan=3_000)
    simulate_session(tmp_path / "a", config)
    simulate_session(tmp_path / "b", config)
    first, second = session_files(tmp_path / "a"), session_files(tmp_path / "b")
    assert first == second
    assert {"scan000.3d", "scan003.pose", "ground_truth_kitti.txt", "odometry_kitti.txt", "simulation.json"} <= set(
        first
    )
    other = SimulationConfig(seed=12, scans=4, points_per_scan=3_000)
    simulate_session(tmp_path / "c", other)
    third = session_files(tmp_path / "c")
    assert third["scan000.3d"] != first["scan000.3d"]
    assert third["ground_truth_kitti.txt"] != first["ground_truth_kitti.txt"]


def test_session_reads_back_with_the_odometry_as_poses(session: SimulatedSession) -> None:
    sequence = read_sequence(session.directory, "uos")
    assert len(sequence) == SMALL.scans
    for scan, odometry, count in zip(sequence, session.odometry, session.point_counts, strict=True):
        assert scan.has_pose
        metres, radians = pose_difference(scan.pose, odometry)
        assert metres < 1e-6 and radians < 1e-6
        assert len(scan) == count
        ranges = np.linalg.norm(scan.points, axis=1)
        assert ranges.min() >= SMALL.min_range - 1e-3 and ranges.max() <= SMALL.max_range + 1e-3
    for name, expected in (("ground_truth_kitti.txt", session.ground_truth), ("odometry_kitti.txt", session.odometry)):
        native = read_kitti_poses(session.directory / name)
        assert len(native) == len(expected)
        for read, pose in zip(native, expected, strict=True):
            np.testing.assert_allclose(UOS.pose_to_canonical(read), pose, atol=1e-8)
    # Ground truth in the KITTI file is in the .pose files' frame and units (cm, uos axes).
    np.testing.assert_allclose(
        read_kitti_poses(session.directory / "odometry_kitti.txt")[3][:3, 3],
        UOS.pose_to_native(sequence[3].pose)[:3, 3],
        atol=1e-4,
    )


def test_ground_truth_puts_every_point_on_the_simulated_surfaces(session: SimulatedSession) -> None:
    scene = build_scene(SMALL, np.random.default_rng(SMALL.seed))  # the session's scene, rebuilt from its seed
    surfaces = o3d.t.geometry.RaycastingScene()
    surfaces.add_triangles(o3d.core.Tensor(scene.vertices), o3d.core.Tensor(scene.triangles))
    sequence = read_sequence(session.directory, "uos")

    def distances(index: int, poses: list[np.ndarray]) -> np.ndarray:
        world = transform_points(poses[index], sequence[index].points).astype(np.float32)
        return surfaces.compute_distance(o3d.core.Tensor(world)).numpy()

    for index in (0, 5, len(sequence) - 1):
        on_surface = distances(index, session.ground_truth)
        assert np.median(on_surface) < 0.005  # 1 cm range noise, seen along the surface normal
        assert np.percentile(on_surface, 95) < 0.025
    assert np.median(distances(len(sequence) - 1, session.odometry)) > 0.05


def test_ground_truth_places_overlapping_scans_onto_each_other(session: SimulatedSession) -> None:
    sequence = read_sequence(session.directory, "uos")

    def placed(index: int, poses: list[np.ndarray], near_to: int) -> np.ndarray:
        """Points of scan ``index`` within 12 m of both scanners, where sampling is dense enough to compare."""
        world = transform_points(poses[index], sequence[index].points)
        keep = (np.linalg.norm(sequence[index].points, axis=1) < 12.0) & (
            np.linalg.norm(world - poses[near_to][:3, 3], axis=1) < 12.0
        )
        return world[keep]

    truth, odometry, last = session.ground_truth, session.odometry, len(sequence) - 1
    for i, j in ((0, 1), (4, 5), (0, last)):
        assert point_to_plane_median(placed(i, truth, j), placed(j, truth, i)) < 0.03
    # Odometry has drifted by the time the loop closes: the same surfaces no longer coincide.
    assert point_to_plane_median(placed(0, odometry, last), placed(last, odometry, 0)) > 0.05


def test_path_is_a_closed_loop_over_uneven_ground(session: SimulatedSession) -> None:
    truth = session.ground_truth
    positions = np.array([p[:3, 3] for p in truth])
    metres, radians = pose_difference(truth[-1], truth[0])
    assert metres < 1.0 and np.degrees(radians) < 15.0
    assert np.linalg.norm(positions[:, :2] - positions[0, :2], axis=1).max() > 20.0
    tilts = np.degrees(np.array([xyzrpy_from_pose(p)[3:5] for p in truth]))
    assert np.abs(tilts).max() > 2.0
    assert np.ptp(positions[:, 2]) > 0.2


def test_odometry_starts_true_then_drifts(session: SimulatedSession) -> None:
    np.testing.assert_allclose(session.odometry[0], session.ground_truth[0])
    drift = absolute_trajectory_error(session.odometry, session.ground_truth)
    assert drift.rmse > 0.5
    # Per step it stays within what scan matching can correct.
    steps = relative_pose_error(session.odometry, session.ground_truth)
    assert 0.02 < steps.translation_rmse < 1.0
    assert 0.2 < steps.rotation_rmse_deg < 8.0


def test_tilting_pattern_sees_only_the_front_half(tmp_path: Path) -> None:
    config = SimulationConfig(seed=1, scans=2, points_per_scan=2_000, pattern="tilting")
    simulate_session(tmp_path, config)
    points = read_sequence(tmp_path, "uos")[0].points
    assert points[:, 0].min() > -0.05  # canonical x is forward
    assert np.abs(points[:, 1]).max() > 5.0


def test_existing_scans_are_not_silently_mixed_in(tmp_path: Path) -> None:
    simulate_session(tmp_path, SimulationConfig(seed=2, scans=5, points_per_scan=1_000))
    smaller = SimulationConfig(seed=2, scans=3, points_per_scan=1_000)
    with pytest.raises(Slam6dError, match="already holds 10 scan file"):
        simulate_session(tmp_path, smaller)
    simulate_session(tmp_path, smaller, overwrite=True)
    assert len(read_sequence(tmp_path, "uos")) == 3
    assert not (tmp_path / "scan004.3d").exists()


def test_invalid_configurations_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="at least 2 scans"):
        simulate_session(tmp_path, SimulationConfig(scans=1))
    with pytest.raises(ValueError, match="unknown scan pattern"):
        simulate_session(tmp_path, SimulationConfig(pattern="spiral"))


def test_progress_is_reported_per_scan(tmp_path: Path) -> None:
    calls: list[tuple[int, int]] = []
    simulate_session(
        tmp_path, SimulationConfig(scans=3, points_per_scan=500), progress=lambda d, t: calls.append((d, t))
    )
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_simulate_command_writes_a_session(tmp_path: Path) -> None:
    out = tmp_path / "cli"
    result = CliRunner().invoke(app, ["simulate", str(out), "--seed", "4", "--scans", "3", "--points-per-scan", "900"])
    assert result.exit_code == 0, result.output
    assert "3 scans" in result.output and "ATE rmse" in result.output
    assert len(read_sequence(out, "uos")) == 3
    again = CliRunner().invoke(app, ["simulate", str(out), "--scans", "3"])
    assert isinstance(again.exception, Slam6dError)
    bad = CliRunner().invoke(app, ["simulate", str(tmp_path / "x"), "--scans", "1"])
    assert bad.exit_code == 2 and "at least 2 scans" in bad.output


def test_bundled_demo_session_is_what_its_readme_command_writes(tmp_path: Path) -> None:
    """sessions/demo/README.md names the command; a simulator change must come with a regenerated demo."""
    demo = Path(__file__).resolve().parent.parent / "sessions" / "demo" / "scans"
    config = SimulationConfig(seed=42, scans=16, points_per_scan=18_000)
    assert "--seed 42 --scans 16 --points-per-scan 18000" in (demo.parent / "README.md").read_text()
    simulate_session(tmp_path, config)
    bundled, fresh = read_sequence(demo, "uos"), read_sequence(tmp_path, "uos")
    assert len(bundled) == len(fresh) == 16
    for old, new in zip(bundled, fresh, strict=True):
        # Compared as numbers, not bytes: another CPU may round a last float32 digit differently.
        assert len(old) == len(new)
        np.testing.assert_allclose(old.points, new.points, atol=2e-4)
        np.testing.assert_allclose(old.pose, new.pose, atol=1e-6)
    for name in ("ground_truth_kitti.txt", "odometry_kitti.txt"):
        np.testing.assert_allclose(read_kitti_poses(demo / name), read_kitti_poses(tmp_path / name), atol=1e-6)
