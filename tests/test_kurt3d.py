"""The uos conventions, end to end: our registration of 3DTK's own three Kurt3D scans must land on
3DTK's ``slam6D`` result (run with ``-a 2 -m 500 -d 25 -i 100``: SVD, 5 m range, 25 cm pairs)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from slam6d.cli import app
from slam6d.geometry import UOS, pose_difference
from slam6d.icp import ICPConfig
from slam6d.io import ReadOptions, read_scan
from slam6d.io.frames import final_frame_pose
from slam6d.pair import register_pair

pytestmark = pytest.mark.slow

# The settings of the reference run, in our terms.
REFERENCE_ICP = ICPConfig(
    method="point_to_point", max_distance=0.25, max_iterations=100, epsilon=1e-7, data_voxel_size=0
)


def reference_pose(folder: Path, index: int) -> np.ndarray:
    return UOS.pose_to_canonical(final_frame_pose(folder / "slam6D_reference" / f"scan{index:03d}.frames"))


def test_three_scans_in_sequence_land_on_3dtk_result(shared_data: Path) -> None:
    folder = shared_data / "kurt3d_3dtk"
    scans = [read_scan(folder / f"scan{i:03d}.3d", "uos", ReadOptions(max_range=500.0)) for i in range(3)]
    poses = [scans[0].pose]
    for previous, current in itertools.pairwise(scans):
        # Odometry increment on top of the previous registration: the seed's extrapolation, pairwise.
        result = register_pair(previous, current, guess="none", icp_config=REFERENCE_ICP)
        poses.append(poses[-1] @ result.transform)
    for index in (1, 2):
        translation, rotation = pose_difference(poses[index], reference_pose(folder, index))
        assert translation < 0.02, f"scan {index}: {translation * 100:.2f} cm from 3DTK"
        assert np.degrees(rotation) < 0.3, f"scan {index}: {np.degrees(rotation):.3f}° from 3DTK"
    # The odometry alone is ~11 cm / 0.8° off for scan 2 (the data README): the test can tell.
    assert pose_difference(scans[2].pose, reference_pose(folder, 2))[0] > 0.05


def test_match_prints_the_transform_in_centimetres_and_the_uos_frame(shared_data: Path) -> None:
    folder = shared_data / "kurt3d_3dtk"
    args = ["match", str(folder / "scan000.3d"), str(folder / "scan001.3d"), "--format", "uos"]
    args += ["--max-range", "500", "--method", "point_to_point", "--iterations", "100", "--voxel", "0"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    rows = [line.split() for line in result.stdout.strip().splitlines()[:4]]
    matrix = np.array(rows, dtype=float)
    # Scan 0 sits at the origin, so the transform is scan 1's native pose in 3DTK's own terms (cm).
    expected = final_frame_pose(folder / "slam6D_reference" / "scan001.frames")
    assert matrix.shape == (4, 4)
    assert np.allclose(matrix[3], [0, 0, 0, 1])
    assert np.linalg.norm(matrix[:3, 3] - expected[:3, 3]) < 2.0  # cm
    assert np.allclose(matrix[:3, :3], expected[:3, :3], atol=5e-3)


def test_match_names_a_missing_file(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["match", str(tmp_path / "nope.3d"), str(tmp_path / "nope2.3d")])
    assert result.exit_code != 0
    assert "nope.3d" in str(result.exception) + result.output
