"""ATE and RPE on trajectories whose errors are known by construction."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from slam6d.cli import app
from slam6d.errors import FormatError, Slam6dError
from slam6d.geometry import invert, pose_from_xyzrpy
from slam6d.io.poses import write_kitti_poses
from slam6d.metrics import (
    absolute_trajectory_error,
    evaluate_trajectory,
    relative_pose_error,
    rigid_alignment,
)
from slam6d.trace import to_jsonable


def loop_trajectory(n: int = 24, radius: float = 10.0) -> list[np.ndarray]:
    """A circle with some height and tilt, so alignment has to get all six dimensions right."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / n
        poses.append(
            pose_from_xyzrpy(
                radius * np.cos(a), radius * np.sin(a), 0.5 * np.sin(2 * a), 0.05 * np.cos(a), 0.03, a + np.pi / 2
            )
        )
    return poses


def test_identical_trajectories_have_zero_error() -> None:
    poses = loop_trajectory()
    result = evaluate_trajectory(poses, poses)
    assert result.ate.rmse == pytest.approx(0.0, abs=1e-9)
    assert result.ate.max == pytest.approx(0.0, abs=1e-9)
    assert result.rpe.translation_rmse == pytest.approx(0.0, abs=1e-9)
    assert result.rpe.rotation_rmse_deg == pytest.approx(0.0, abs=1e-5)
    assert result.ate.count == 24 and result.rpe.count == 23


def test_rigidly_moved_trajectory_vanishes_after_alignment_only() -> None:
    reference = loop_trajectory()
    offset = pose_from_xyzrpy(3.0, -2.0, 1.0, 0.1, -0.2, 0.7)
    estimate = [offset @ p for p in reference]
    aligned = absolute_trajectory_error(estimate, reference, align=True)
    assert aligned.rmse == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(aligned.alignment, invert(offset), atol=1e-9)
    raw = absolute_trajectory_error(estimate, reference, align=False)
    assert raw.rmse > 1.0
    # RPE only sees motions, which a common rigid offset does not change.
    assert relative_pose_error(estimate, reference).translation_rmse == pytest.approx(0.0, abs=1e-9)


def test_constant_translation_offset_without_alignment_equals_offset() -> None:
    reference = loop_trajectory()
    estimate = [pose_from_xyzrpy(0.3, 0.4, 0.0, 0, 0, 0) @ p for p in reference]
    raw = absolute_trajectory_error(estimate, reference, align=False)
    assert raw.rmse == pytest.approx(0.5)
    assert raw.mean == pytest.approx(0.5) and raw.median == pytest.approx(0.5) and raw.max == pytest.approx(0.5)
    assert absolute_trajectory_error(estimate, reference).rmse == pytest.approx(0.0, abs=1e-9)


def test_linear_drift_has_the_analytic_error() -> None:
    """Positions drifting by k·d along x: with no alignment, errors are 0, d, 2d, ...; rmse is analytic."""
    n, d = 11, 0.1
    reference = [pose_from_xyzrpy(i * 1.0, 0, 0, 0, 0, 0) for i in range(n)]
    estimate = [pose_from_xyzrpy(i * (1.0 + d), 0, 0, 0, 0, 0) for i in range(n)]
    raw = absolute_trajectory_error(estimate, reference, align=False)
    expected = d * np.arange(n)
    assert raw.rmse == pytest.approx(np.sqrt(np.mean(expected**2)))
    assert raw.max == pytest.approx(d * (n - 1))
    assert raw.median == pytest.approx(d * 5)
    # Alignment can only shift a scale error, leaving errors symmetric about the middle.
    aligned = absolute_trajectory_error(estimate, reference)
    centred = d * (np.arange(n) - (n - 1) / 2)
    assert aligned.rmse == pytest.approx(np.sqrt(np.mean(centred**2)))
    rpe = relative_pose_error(estimate, reference)
    assert rpe.translation_rmse == pytest.approx(d)
    assert relative_pose_error(estimate, reference, delta=3).translation_rmse == pytest.approx(3 * d)


def test_rpe_of_a_known_per_step_error() -> None:
    """Each step of the estimate over-turns by 1° and overshoots 2 cm: RPE reports exactly that."""
    reference = loop_trajectory(n=30)
    step_error = pose_from_xyzrpy(0.02, 0.0, 0.0, 0.0, 0.0, np.radians(1.0))
    estimate = [reference[0]]
    for i in range(1, len(reference)):
        estimate.append(estimate[-1] @ invert(reference[i - 1]) @ reference[i] @ step_error)
    rpe = relative_pose_error(estimate, reference)
    assert rpe.translation_rmse == pytest.approx(0.02, abs=1e-9)
    assert rpe.rotation_rmse_deg == pytest.approx(1.0, abs=1e-6)
    assert rpe.rotation_max_deg == pytest.approx(1.0, abs=1e-6)
    # The errors accumulate into a global drift that ATE sees even after alignment.
    assert absolute_trajectory_error(estimate, reference).rmse > 0.5


def test_alignment_is_a_proper_rotation_for_planar_and_degenerate_inputs() -> None:
    rng = np.random.default_rng(3)
    planar = np.c_[rng.normal(size=(10, 2)), np.zeros(10)]
    t = rigid_alignment(planar, planar[:, [1, 0, 2]])  # a mirror image: best fit must not reflect
    assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0)
    single = rigid_alignment(np.zeros((1, 3)), np.ones((1, 3)))
    np.testing.assert_allclose(single[:3, 3], 1.0)


def test_mismatched_lengths_are_refused() -> None:
    poses = loop_trajectory()
    with pytest.raises(Slam6dError, match="24 poses but reference has 23"):
        absolute_trajectory_error(poses, poses[:-1])
    with pytest.raises(Slam6dError, match="delta 30"):
        relative_pose_error(poses, poses, delta=30)


def test_results_serialise_to_json() -> None:
    poses = loop_trajectory()
    data = to_jsonable(evaluate_trajectory(poses, poses))
    assert set(data) == {"ate", "rpe"}
    assert data["ate"]["count"] == 24 and len(data["ate"]["errors"]) == 24
    assert data["rpe"]["delta"] == 1


def test_eval_command_reports_ate_and_rpe_in_file_units(tmp_path: Path) -> None:
    """Poses in cm with a constant 30/40 cm offset: ATE 50 cm unaligned, 0 aligned; RPE 0."""
    reference = [pose_from_xyzrpy(100 * p[0, 3], 100 * p[1, 3], 100 * p[2, 3], 0, 0, 0) for p in loop_trajectory()]
    estimate = [pose_from_xyzrpy(30.0, 40.0, 0.0, 0, 0, 0) @ p for p in reference]
    write_kitti_poses(tmp_path / "ref.txt", reference)
    write_kitti_poses(tmp_path / "est.txt", estimate)
    runner = CliRunner()
    args = ["eval", str(tmp_path / "est.txt"), str(tmp_path / "ref.txt")]
    raw = runner.invoke(app, [*args, "--no-align", "--units-per-metre", "100"])
    assert raw.exit_code == 0, raw.output
    assert "24 poses" in raw.output and "not aligned" in raw.output
    assert "rmse    50.0000 (0.5000 m)" in raw.output
    aligned = runner.invoke(app, [*args, "--json"])
    data = json.loads(aligned.output)
    assert data["ate"]["rmse"] == pytest.approx(0.0, abs=1e-6)
    assert data["rpe"]["translation_rmse"] == pytest.approx(0.0, abs=1e-6)

    write_kitti_poses(tmp_path / "short.txt", reference[:20])
    short = runner.invoke(app, ["eval", str(tmp_path / "short.txt"), str(tmp_path / "ref.txt")])
    assert isinstance(short.exception, FormatError)
    assert "short.txt" in str(short.exception) and "ref.txt" in str(short.exception)
    assert "20 poses" in str(short.exception) and "24" in str(short.exception)
