"""The measured tilt (slam6d.attitude): an inclinometer's up as a prior on each scan's roll and pitch,
in sequential ICP, the pose graph and loop closing, and only where the session declares one."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from slam6d.attitude import (
    PLANES_TILT_DEG,
    RINGS_TILT_DEG,
    UP,
    TiltPrior,
    declared_tilt_noise,
    heading_only,
    measured_up,
    tilt_error_deg,
    tilt_information,
)
from slam6d.errors import Slam6dError
from slam6d.geometry import invert, make_pose, pose_from_xyzrpy, rot_x, rot_y, so3_exp, xyzrpy_from_pose
from slam6d.icp import ICPConfig, icp_iterations
from slam6d.io.registry import read_sequence
from slam6d.loops import LoopHypothesis, hold_closed_loops
from slam6d.pipeline import Pipeline, PipelineConfig
from slam6d.posegraph import PoseEdge, optimize_pose_graph
from slam6d.simulate import SimulationConfig, simulate_session


def _room(rng: np.random.Generator) -> np.ndarray:
    """Points on the six walls of a 10 x 10 x 4 m room around the scanner: every rotation is fixed
    by many pairs, roll and pitch alike (the room is square, so both hold the same information)."""
    faces = []
    for axis, (low, high) in enumerate([(-5.0, 5.0), (-5.0, 5.0), (-1.5, 2.5)]):
        for value in (low, high):
            pts = rng.uniform([-5.0, -5.0, -1.5], [5.0, 5.0, 2.5], (1500, 3))
            pts[:, axis] = value
            faces.append(pts)
    return np.vstack(faces)


def test_icp_mixes_its_tilt_and_the_reading_by_their_stated_accuracies() -> None:
    """An exact copy of a room matched from the truth stays at the truth; given a reading 0.5° off
    in pitch, the fit moves towards it by the reading's share of the combined information,
    r / (1 + r) with r = TiltPrior.sequential_ratio (0.39 at 0.1° against 0.3°: 0.141°), and
    keeps its heading and position (a turn about the scanner, not a shift). A fit worth 0.006° a
    step (scans that find their planes alone) moves 0.03° at most."""
    points = _room(np.random.default_rng(1))
    prior = TiltPrior.from_poses(
        [pose_from_xyzrpy(0, 0, 0, 0.0, math.radians(0.5), 0.3)], [True], 0.3, registration_deg=RINGS_TILT_DEG
    )
    tilt = prior.for_fit(0, np.eye(4))
    assert tilt is not None
    config = ICPConfig(data_voxel_size=0.0, normal_voxel_size=0.0, max_distance=0.3)
    plain = list(icp_iterations(points, points, np.eye(4), config))[-1].transform
    held = list(icp_iterations(points, points, np.eye(4), config, tilt=tilt))[-1].transform
    assert tilt_error_deg(plain, UP) < 1e-4
    ratio = prior.sequential_ratio(0)
    assert ratio == pytest.approx(0.393, abs=0.001)
    expected = 0.5 * ratio / (1.0 + ratio)
    _, _, _, roll, pitch, yaw = xyzrpy_from_pose(held)
    assert math.degrees(pitch) == pytest.approx(expected, abs=0.01)
    assert abs(math.degrees(roll)) < 0.01 and abs(math.degrees(yaw)) < 0.01
    assert np.linalg.norm(held[:3, 3]) < 0.005
    prior.registered_with(0, PLANES_TILT_DEG)
    dense = list(icp_iterations(points, points, np.eye(4), config, tilt=prior.for_fit(0, np.eye(4))))[-1].transform
    assert tilt_error_deg(dense, UP) < 0.03


def _arc_with_pitch_drift(
    steps: int = 41,
) -> tuple[list[np.ndarray], list[np.ndarray], list[PoseEdge]]:
    """The campus's failure as a pose graph: 3.1 m steps along a flat 100 m-radius arc, every
    step's relative pose tilted by the same 0.1° of pitch (the registration's bias on ring scans),
    and each edge claiming far more rotational certainty than that (point pairs' information)."""
    angles = np.linspace(0.0, 2 * np.pi, 200, endpoint=False)[: steps + 1]
    truth = [pose_from_xyzrpy(100 * np.cos(a), 100 * np.sin(a), 0.0, 0.0, 0.0, a + np.pi / 2) for a in angles]
    bias = make_pose(so3_exp(np.array([0.0, np.radians(0.1), 0.0])), np.zeros(3))
    measured = [invert(truth[k]) @ truth[k + 1] @ bias for k in range(steps)]
    chained = [truth[0]]
    for step in measured:
        chained.append(chained[-1] @ step)
    information = np.diag([1e4, 1e4, 1e4, 1e8, 1e8, 1e8])
    return truth, chained, [PoseEdge(k, k + 1, measured[k], information) for k in range(steps)]


def test_tilt_prior_takes_a_steady_pitch_drift_out_of_a_pose_graph_without_loops() -> None:
    """No loop edge, only the drifting steps and an inclinometer reading per pose (0.3° noise):
    the path that climbed 3.9 m stays within 0.6 m of the flat truth everywhere and its tilt
    within 0.35° of the truth at every pose (RMS under 0.2°); without the readings the same solve
    keeps the climb. The remaining height is the readings' noise integrated over 130 m, not the bias."""
    truth, chained, edges = _arc_with_pitch_drift()
    assert max(abs(c[2, 3] - t[2, 3]) for c, t in zip(chained, truth, strict=True)) > 3.5
    rng = np.random.default_rng(7)
    readings = [
        t @ make_pose(rot_x(rng.normal(0.0, math.radians(0.3))) @ rot_y(rng.normal(0.0, math.radians(0.3))), [0, 0, 0])
        for t in truth
    ]
    prior = TiltPrior.from_poses(readings, [True] * len(truth), 0.3, registration_deg=RINGS_TILT_DEG)
    free = optimize_pose_graph(chained, edges, fixed=[0])
    held = optimize_pose_graph(chained, edges, fixed=[0], tilt=prior)
    assert max(abs(p[2, 3] - t[2, 3]) for p, t in zip(free.poses, truth, strict=True)) > 3.5
    height = [abs(p[2, 3] - t[2, 3]) for p, t in zip(held.poses, truth, strict=True)]
    tilt = [tilt_error_deg(p, measured_up(t)) for p, t in zip(held.poses, truth, strict=True)]
    assert max(height) < 0.6, max(height)
    assert max(tilt) < 0.35 and math.sqrt(np.mean(np.square(tilt))) < 0.2, tilt


def test_a_pose_graph_without_readings_is_solved_as_before() -> None:
    """Readings flagged as not measured (a scan without odometry) leave the solve untouched."""
    truth, chained, edges = _arc_with_pitch_drift(12)
    prior = TiltPrior.from_poses(truth, [False] * len(truth), 0.3)
    plain = optimize_pose_graph(chained, edges, fixed=[0])
    unread = optimize_pose_graph(chained, edges, fixed=[0], tilt=prior)
    for a, b in zip(plain.poses, unread.poses, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_heading_only_keeps_the_tilt_and_the_loop_end() -> None:
    """A loop correction that turns 3° about up and tilts 0.4° loses the tilt, keeps the turn, and
    still puts the loop's end where the full correction does."""
    full = make_pose(so3_exp(np.array([np.radians(0.3), np.radians(-0.25), np.radians(3.0)])), [1.0, -2.0, 0.4])
    end = np.array([120.0, 40.0, 3.0])
    level = heading_only(full, end)
    np.testing.assert_allclose(level[:3, :3] @ UP, UP, atol=1e-12)
    np.testing.assert_allclose(level[:3, :3] @ end + level[:3, 3], full[:3, :3] @ end + full[:3, 3], atol=1e-9)
    assert math.degrees(xyzrpy_from_pose(level)[5]) == pytest.approx(3.0, abs=0.02)


def test_the_simulator_declares_its_inclinometer_and_nothing_else_does(tmp_path: Path) -> None:
    """simulation.json names the inclinometer the odometry carries; a session without odometry, a
    folder of another origin (Kurt3D's .pose files from 2D wheel odometry) and a simulation.json
    of another generator declare none; a malformed declaration is an error naming the file."""
    small = {"scans": 2, "points_per_scan": 500, "loop_length": 16.0, "loop_width": 10.0}
    with_odometry = simulate_session(tmp_path / "odo", SimulationConfig(**small))  # type: ignore[arg-type]
    meta = json.loads(with_odometry.parameters_file.read_text())
    assert meta["inclinometer"] == {"roll_pitch_noise_deg": 0.3}
    assert declared_tilt_noise(tmp_path / "odo") == 0.3
    simulate_session(tmp_path / "none", SimulationConfig(odometry=False, **small))  # type: ignore[arg-type]
    assert declared_tilt_noise(tmp_path / "none") is None
    (tmp_path / "kurt").mkdir()
    assert declared_tilt_noise(tmp_path / "kurt") is None
    (tmp_path / "kurt" / "simulation.json").write_text(json.dumps({"generator": "another tool", "inclinometer": {}}))
    assert declared_tilt_noise(tmp_path / "kurt") is None
    meta["inclinometer"] = {"roll_pitch_noise_deg": -1}
    with_odometry.parameters_file.write_text(json.dumps(meta))
    with pytest.raises(Slam6dError, match=r"simulation\.json.*roll_pitch_noise_deg"):
        declared_tilt_noise(tmp_path / "odo")


def test_a_run_uses_the_tilt_only_where_it_is_declared(tmp_path: Path) -> None:
    """Without ``tilt_noise_deg`` (the default: odometry of unknown kind) the pipeline holds no
    readings and registers exactly as before; with it, only the scans that have odometry carry one;
    a session without odometry has nothing to hold."""
    small = {"scans": 3, "points_per_scan": 4000, "loop_length": 16.0, "loop_width": 10.0, "seed": 2}
    simulate_session(tmp_path / "odo", SimulationConfig(**small))  # type: ignore[arg-type]
    sequence = read_sequence(tmp_path / "odo", "uos")
    assert Pipeline(sequence, PipelineConfig(loops=False, relaxation="none")).tilt is None
    held = Pipeline(sequence, PipelineConfig(loops=False, relaxation="none", tilt_noise_deg=0.3))
    assert held.tilt is not None and held.tilt.measured.all() and held.tilt.noise_deg == 0.3
    simulate_session(tmp_path / "none", SimulationConfig(odometry=False, **small))  # type: ignore[arg-type]
    blind = read_sequence(tmp_path / "none", "uos")
    assert Pipeline(blind, PipelineConfig(loops=False, relaxation="none", tilt_noise_deg=0.3)).tilt is None
    with pytest.raises(ValueError, match="tilt_noise_deg"):
        PipelineConfig(tilt_noise_deg=0.0)


def test_a_session_over_a_simulated_folder_writes_its_inclinometer_into_engine(tmp_path: Path) -> None:
    """The workbench runs with a session's [engine] settings: a session made over a folder that
    declares an inclinometer says so there (and the user's own value wins); over any other folder
    nothing is added."""
    from slam6d.engine_settings import pipeline_config
    from slam6d.session import Session

    small = {"scans": 2, "points_per_scan": 500, "loop_length": 16.0, "loop_width": 10.0}
    simulate_session(tmp_path / "odo", SimulationConfig(**small))  # type: ignore[arg-type]
    simulate_session(tmp_path / "none", SimulationConfig(odometry=False, **small))  # type: ignore[arg-type]
    declared = Session.create(tmp_path / "s1", "declared", tmp_path / "odo")
    assert declared.config.engine["tilt_noise_deg"] == 0.3
    assert pipeline_config(declared.config.engine).tilt_noise_deg == 0.3
    chosen = Session.create(tmp_path / "s2", "chosen", tmp_path / "odo", engine={"tilt_noise_deg": 1.0})
    assert chosen.config.engine["tilt_noise_deg"] == 1.0
    blind = Session.create(tmp_path / "s3", "blind", tmp_path / "none")
    assert "tilt_noise_deg" not in blind.config.engine


def test_holding_closed_loops_keeps_the_measured_tilt() -> None:
    """The joint loop holding (slam6d.loops.hold_closed_loops) solves the registered steps and the
    closed loops as one pose graph; with readings it holds them as the relaxation does. On the
    drifting arc with one loop over 60 steps whose verified transform is itself 0.3° off in pitch
    (as the campus's ring-scan loops were before they were verified fused), the held poses stay
    within 0.35° of the true tilt (RMS under 0.15°) and 0.15 m of the flat truth's height; without
    the readings the steps' 0.1° per step stays in them (measured 1.2° off at worst, RMS 0.86°)."""
    truth, chained, _ = _arc_with_pitch_drift(60)
    tilted = make_pose(rot_y(math.radians(0.3)), [0.0, 0.0, 0.0])
    loop = LoopHypothesis(0, 60, 0.0, 186.0, transform=invert(truth[0]) @ truth[60] @ tilted, accepted=True)
    rng = np.random.default_rng(11)
    readings = [
        t @ make_pose(rot_x(rng.normal(0.0, math.radians(0.3))) @ rot_y(rng.normal(0.0, math.radians(0.3))), [0, 0, 0])
        for t in truth
    ]
    prior = TiltPrior.from_poses(readings, [True] * len(truth), 0.3, registration_deg=RINGS_TILT_DEG)
    lever = 10.0
    free = hold_closed_loops(chained, [loop], chained, lever)
    held = hold_closed_loops(chained, [loop], chained, lever, tilt=prior)
    assert max(tilt_error_deg(p, measured_up(t)) for p, t in zip(free, truth, strict=True)) > 0.8
    tilt = [tilt_error_deg(p, measured_up(t)) for p, t in zip(held, truth, strict=True)]
    assert max(tilt) < 0.35 and math.sqrt(np.mean(np.square(tilt))) < 0.15, tilt
    assert max(abs(p[2, 3] - t[2, 3]) for p, t in zip(held, truth, strict=True)) < 0.15


def test_tilt_information_of_many_systems_at_once_is_each_ones_schur_complement_across_up() -> None:
    """What LUM and the pose graph weigh every scan's reading by, computed for all scans in one
    call: each value is the information on the two axes across that scan's up once its translation
    is free, and a system whose translation holds nothing keeps its rotation block."""
    rng = np.random.default_rng(4)
    count = 7
    factors = rng.normal(size=(count, 9, 6))
    hessians = np.einsum("nki,nkj->nij", factors, factors)  # positive definite 6x6, rotation first
    hessians[2, 3:, :] = 0.0  # one scan whose pairs hold no translation: its rotation alone counts
    hessians[2, :, 3:] = 0.0
    ups = rng.normal(size=(count, 3))
    ups /= np.linalg.norm(ups, axis=1, keepdims=True)
    many = tilt_information(hessians, ups)
    assert many.shape == (count,)
    for k in range(count):
        rotation, mixed, translation = hessians[k, :3, :3], hessians[k, :3, 3:], hessians[k, 3:, 3:]
        reduced = rotation if k == 2 else rotation - mixed @ np.linalg.inv(translation) @ mixed.T
        # the two axes across up: any orthonormal pair perpendicular to it
        across = np.linalg.svd(np.eye(3) - np.outer(ups[k], ups[k]))[0][:, :2]
        expected = np.trace(across.T @ reduced @ across) / 2.0
        assert many[k] == pytest.approx(expected, rel=1e-9)
        assert float(tilt_information(hessians[k], ups[k])) == pytest.approx(expected, rel=1e-12)
    # a shift that undoes a tilt is no information on it: a rotation block fully explained by the
    # translation's coupling leaves nothing
    lever = rng.normal(size=(3, 3))
    coupled = np.block([[lever @ lever.T, lever], [lever.T, np.eye(3)]])
    assert float(tilt_information(coupled, np.array([0.0, 0.0, 1.0]))) == pytest.approx(0.0, abs=1e-12)
