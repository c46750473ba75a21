"""The simulator writes sessions whose ground truth is consistent, whose odometry drifts, and which reproduce."""

from __future__ import annotations

import json
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
from slam6d.sensors import get_sensor
from slam6d.simulate import (
    SimulatedSession,
    Simulation,
    SimulationConfig,
    build_scene,
    simulate_session,
    simulated_scans,
)

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
        assert ranges.min() >= SMALL.min_range - 1e-3 and ranges.max() <= 30.0 + 1e-3  # the SICK's range
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
    config = SimulationConfig(seed=1, scans=2, points_per_scan=2_000, sensor="tilting-sick")
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
    with pytest.raises(ValueError, match="unknown sensor 'spiral'; choose one of rotating-sick"):
        simulate_session(tmp_path, SimulationConfig(sensor="spiral"))
    with pytest.raises(ValueError, match="unknown world 'moon'"):
        simulate_session(tmp_path, SimulationConfig(world="moon"))
    with pytest.raises(ValueError, match="unknown motion 'skate'"):
        simulate_session(tmp_path, SimulationConfig(motion="skate"))
    with pytest.raises(ValueError, match=r"at least one laser per column \(16\) for vlp16"):
        simulate_session(tmp_path, SimulationConfig(sensor="vlp16", points_per_scan=10))


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


# ---------------------------------------------------------------- sensors, worlds, motions


def elevations_deg(points: np.ndarray) -> np.ndarray:
    """Elevation of each point above the scanner's horizontal plane (canonical frame: z up)."""
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


DEVICES = {  # name: beams, lowest and highest elevation (°) as the manufacturers publish them
    "vlp16": (16, -15.0, 15.0),
    "hdl32": (32, -30.67, 10.67),
    "hdl64": (64, -24.9, 2.0),
    "os1-64": (64, -16.6, 16.6),
}


@pytest.mark.parametrize("name", list(DEVICES))
def test_multi_beam_sensor_writes_its_rings(tmp_path: Path, name: str) -> None:
    """Read back from the files, the points' elevations fall on the device's beam angles, every
    laser shows up, and the first column comes in the device's firing order."""
    beams, lowest, highest = DEVICES[name]
    columns = 360
    config = SimulationConfig(seed=5, scans=2, world="indoor", sensor=name, points_per_scan=beams * columns)
    simulate_session(tmp_path, config)
    points = read_sequence(tmp_path, "uos")[0].points
    elevation = elevations_deg(points)
    table = np.array(get_sensor(name).elevations_deg)
    nearest = np.abs(elevation[:, None] - table[None, :]).argmin(axis=1)
    assert np.abs(elevation - table[nearest]).max() < 0.02  # on a beam, not between beams
    assert len(np.unique(nearest)) == beams  # indoors every laser hits a wall, floor or ceiling
    assert elevation.min() == pytest.approx(lowest, abs=0.02) and elevation.max() == pytest.approx(highest, abs=0.02)
    assert np.all(np.diff(np.sort(table)) > 0.2)  # distinct rings
    # Points come column by column, lasers in firing order; indoors the first column is complete.
    np.testing.assert_array_equal(nearest[:beams], np.arange(beams))
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    assert abs(azimuth[0]) < 0.01 and azimuth[beams] == pytest.approx(-360.0 / columns, abs=0.01)  # clockwise
    assert len(points) == beams * columns


def test_vlp16_fires_its_lasers_interleaved() -> None:
    assert get_sensor("vlp16").elevations_deg == (-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15)
    assert np.allclose(np.diff(np.sort(get_sensor("os1-64").elevations_deg)), 33.2 / 63)  # uniform


def test_sensor_range_and_noise_are_the_devices(tmp_path: Path) -> None:
    """An HDL-64E on the campus sees beyond the SICK's 30 m, up to its own 120 m, with ~2 cm noise."""
    config = SimulationConfig(seed=2, scans=2, world="campus", sensor="hdl64", points_per_scan=64 * 300)
    simulation = simulated_scans(config)
    assert simulation.config.max_range == 120.0 and simulation.config.range_noise == 0.02
    points = next(simulation.scans())
    ranges = np.linalg.norm(points, axis=1)
    assert ranges.max() > 40.0 and ranges.max() <= 120.0
    # The noise lies along each ray: against the noiseless range of the same direction, cast again.
    directions = points / ranges[:, None]
    pose = simulation.truth[0]
    exact = simulation.scene.cast(pose[:3, 3], directions @ pose[:3, :3].T)
    assert np.std(ranges - exact) == pytest.approx(0.02, rel=0.1)


def planar_motion(truth: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Step lengths (m, in the plane) and absolute heading changes (°) between consecutive scans."""
    states = np.array([xyzrpy_from_pose(p) for p in truth])
    steps = np.linalg.norm(np.diff(states[:, :2], axis=0), axis=1)
    turns = np.degrees(np.abs(np.angle(np.exp(1j * np.diff(states[:, 5])))))
    return steps, turns


def test_handheld_indoors_takes_short_steps_and_sharp_turns() -> None:
    simulation = simulated_scans(SimulationConfig(seed=3, scans=120, world="indoor", points_per_scan=16 * 10))
    assert (simulation.config.sensor, simulation.config.motion) == ("vlp16", "handheld")
    steps, turns = planar_motion(simulation.truth)
    assert np.percentile(steps, 5) > 0.2 and np.percentile(steps, 95) < 0.8 and 0.4 < np.median(steps) < 0.6
    assert turns.max() <= 46.0  # the cap, plus what the hand's roll and pitch add to the yaw angle
    assert (turns >= 30.0).sum() >= 5  # doors and corners: turns of 30-45° within half a metre
    states = np.array([xyzrpy_from_pose(p) for p in simulation.truth])
    assert 2.0 < np.degrees(np.std(states[:, 3])) < 6.0  # the hand wobbles
    heights = states[:, 2]
    assert np.all(np.abs(heights - 1.4) < 0.15)


def test_car_outdoors_drives_1_to_3_m_with_smooth_yaw() -> None:
    simulation = simulated_scans(SimulationConfig(seed=3, scans=300, world="outdoor", points_per_scan=32 * 10))
    assert (simulation.config.sensor, simulation.config.motion) == ("hdl32", "car")
    steps, turns = planar_motion(simulation.truth)
    assert steps.min() > 0.9 and steps.max() < 3.1 and 1.6 < steps.mean() < 2.4
    assert np.abs(np.diff(steps)).max() < 1.5  # the speed changes smoothly
    assert np.median(turns) < 1.0 and turns.max() < 60.0  # straight streets, corners over several scans
    assert np.percentile(turns, 99) > 15.0


def test_robot_spreads_its_stops_evenly_over_one_lap() -> None:
    simulation = simulated_scans(
        SimulationConfig(seed=4, scans=40, world="indoor", motion="robot", sensor="rotating-sick", points_per_scan=181)
    )
    route = simulation.scene.route
    stops = [route.at(s)[0] for s in np.linspace(0.0, route.length - 0.6, 40)]  # the last 0.6 m short of the first
    np.testing.assert_allclose([p[:2, 3] for p in simulation.truth], stops, atol=1e-9)  # the floor is level
    assert np.all(np.abs(np.array([p[2, 3] for p in simulation.truth]) - 0.5) < 1e-9)


@pytest.fixture(scope="module")
def campus_drive() -> Simulation:
    """700 scans of the campus drive (its poses; scans are cast only when asked for)."""
    return simulated_scans(SimulationConfig(seed=6, scans=700, world="campus", points_per_scan=16 * 50))


def test_campus_has_levels_loops_and_opposite_revisits(campus_drive: Simulation) -> None:
    positions = np.array([p[:3, 3] for p in campus_drive.truth])
    states = np.array([xyzrpy_from_pose(p) for p in campus_drive.truth])
    assert np.ptp(positions[:, 2]) > 3.5  # up onto the parking deck
    assert np.degrees(np.abs(states[:, 4]).max()) > 6.0  # its ramp pitches the car
    assert np.ptp(positions[:, 0]) > 200.0  # a drive across blocks, not round one
    # Revisits: scans more than 100 apart within 6 m of each other (the other lane of a street, 5 m
    # away, when driving the other way), some in the same direction and some facing the other way.
    distance = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=2)
    i, j = np.nonzero((distance < 6.0) & (np.arange(700)[None, :] - np.arange(700)[:, None] > 100))
    assert len(i) > 20
    facing = np.degrees(np.abs(np.angle(np.exp(1j * (states[j, 5] - states[i, 5])))))
    assert (facing > 150.0).any() and (facing < 30.0).any()
    # The same place at two heights: on the deck's roof and under it.
    stacked = (distance < 4.0) & (np.abs(positions[:, None, 2] - positions[None, :, 2]) > 3.0)
    assert stacked.any()


def test_campus_is_deterministic_by_seed(campus_drive: Simulation) -> None:
    again = simulated_scans(campus_drive.config)
    for a, b in zip(campus_drive.truth, again.truth, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(campus_drive.scene.vertices, again.scene.vertices)
    assert next(again.scans()).tobytes() == next(campus_drive.scans()).tobytes()
    other = simulated_scans(SimulationConfig(seed=7, scans=700, world="campus", points_per_scan=16 * 50))
    assert not np.array_equal(other.truth[-1], again.truth[-1])
    assert len(other.scene.vertices) != len(again.scene.vertices) or not np.array_equal(
        other.scene.vertices, again.scene.vertices
    )


@pytest.mark.parametrize(("world", "index"), [("indoor", 7), ("outdoor", 4), ("campus", 25)])
def test_ground_truth_puts_points_on_every_worlds_surfaces(world: str, index: int) -> None:
    config = SimulationConfig(seed=8, scans=index + 1, world=world, points_per_scan=16 * 200)
    simulation = simulated_scans(config)
    surfaces = o3d.t.geometry.RaycastingScene()
    surfaces.add_triangles(o3d.core.Tensor(simulation.scene.vertices), o3d.core.Tensor(simulation.scene.triangles))
    clouds = list(simulation.scans())
    world_points = transform_points(simulation.truth[index], clouds[index]).astype(np.float32)
    on_surface = surfaces.compute_distance(o3d.core.Tensor(world_points)).numpy()
    assert np.median(on_surface) < 0.02  # 3 cm range noise, seen along the surface normal
    assert np.percentile(on_surface, 90) < 0.06


def test_without_odometry_no_pose_files_and_the_same_scans(tmp_path: Path) -> None:
    config = SimulationConfig(seed=9, scans=4, world="indoor", points_per_scan=16 * 100)
    with_odometry = simulate_session(tmp_path / "with", config)
    without = simulate_session(tmp_path / "without", SimulationConfig(**{**config.__dict__, "odometry": False}))
    assert without.odometry_file is None and with_odometry.odometry_file is not None
    names = {p.name for p in (tmp_path / "without").iterdir()}
    assert not any(name.endswith(".pose") for name in names) and "odometry_kitti.txt" not in names
    for name in ("scan000.3d", "scan003.3d", "ground_truth_kitti.txt"):
        assert (tmp_path / "with" / name).read_bytes() == (tmp_path / "without" / name).read_bytes()
    sequence = read_sequence(tmp_path / "without", "uos")
    assert len(sequence) == 4
    assert not any(scan.has_pose for scan in sequence)
    assert all(np.array_equal(scan.pose, np.eye(4)) for scan in sequence)
    # Overwriting a session with odometry by one without removes its odometry.
    simulate_session(tmp_path / "with", SimulationConfig(**{**config.__dict__, "odometry": False}), overwrite=True)
    assert not (tmp_path / "with" / "odometry_kitti.txt").exists()
    assert not (tmp_path / "with" / "scan000.pose").exists()


def test_simulate_command_takes_sensor_world_motion_and_no_odometry(tmp_path: Path) -> None:
    out = tmp_path / "cli"
    args = ["simulate", str(out), "--world", "indoor", "--sensor", "os1-64", "--motion", "handheld", "--scans", "3"]
    result = CliRunner().invoke(app, [*args, "--points-per-scan", "6400", "--no-odometry"])
    assert result.exit_code == 0, result.output
    assert "no odometry written" in result.output
    parameters = json.loads((out / "simulation.json").read_text())
    assert parameters["config"]["sensor"] == "os1-64" and parameters["config"]["world"] == "indoor"
    assert parameters["config"]["points_per_scan"] == 6400 and parameters["odometry"] is None
    legacy = CliRunner().invoke(app, ["simulate", str(tmp_path / "old"), "--pattern", "tilting", "--scans", "2",
                                      "--points-per-scan", "900"])  # fmt: skip
    assert legacy.exit_code == 0, legacy.output
    assert json.loads((tmp_path / "old" / "simulation.json").read_text())["config"]["sensor"] == "tilting-sick"
    bad = CliRunner().invoke(app, ["simulate", str(tmp_path / "x"), "--sensor", "hdl16"])
    assert bad.exit_code == 2 and "unknown sensor 'hdl16'" in bad.output


def test_sessions_beyond_999_scans_read_back_in_order(tmp_path: Path) -> None:
    config = SimulationConfig(seed=1, scans=1002, world="indoor", motion="robot", sensor="vlp16", points_per_scan=16)
    simulate_session(tmp_path, config)
    sequence = read_sequence(tmp_path, "uos")
    assert len(sequence) == 1002 and sequence[1001].name.startswith("scan1001")
