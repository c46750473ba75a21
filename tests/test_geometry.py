"""Round trips and conventions of the geometry module (property tests over random poses)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slam6d import geometry as g

angles = st.floats(min_value=-np.pi, max_value=np.pi, allow_nan=False)
half_angles = st.floats(min_value=-np.pi / 2 + 1e-3, max_value=np.pi / 2 - 1e-3, allow_nan=False)
coords = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)
fractions = st.floats(min_value=0.0, max_value=1.0)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return g.make_pose(g.quaternion_to_rotation(q), rng.normal(size=3) * 10)


@given(angles, half_angles, angles)
def test_euler_round_trip_reproduces_rotation(rx: float, ry: float, rz: float) -> None:
    rotation = g.euler_to_rotation(rx, ry, rz)
    assert np.allclose(g.euler_to_rotation(*g.rotation_to_euler(rotation)), rotation, atol=1e-9)


def test_euler_order_is_rx_ry_rz_as_in_3dtk() -> None:
    # First line of 3DTK's reference scan001.frames for .pose angles (1.35694, -0.852409, -0.56224) deg.
    rotation = g.uos_pose(np.zeros(3), np.array([1.35694, -0.852409, -0.56224]))[:3, :3]
    columns = np.array(
        [[0.999841, -0.0101623, 0.0146395], [0.0098117, 0.999668, 0.0238257], [-0.0148768, -0.0236782, 0.999609]]
    )
    expected = columns.T
    assert np.allclose(rotation, expected, atol=2e-6)


def test_gimbal_lock_round_trip() -> None:
    rotation = g.euler_to_rotation(0.3, np.pi / 2, -0.2)
    assert np.allclose(g.euler_to_rotation(*g.rotation_to_euler(rotation)), rotation, atol=1e-9)


@given(angles, half_angles, angles, coords, coords, coords)
def test_xyzrpy_round_trip(roll: float, pitch: float, yaw: float, x: float, y: float, z: float) -> None:
    pose = g.pose_from_xyzrpy(x, y, z, roll, pitch, yaw)
    assert np.allclose(g.pose_from_xyzrpy(*g.xyzrpy_from_pose(pose)), pose, atol=1e-7)


@given(st.integers(0, 2**32 - 1))
def test_quaternion_round_trip_and_inverse(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = random_pose(rng)
    q = g.rotation_to_quaternion(pose[:3, :3])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12 and q[0] >= 0
    assert np.allclose(g.quaternion_to_rotation(q), pose[:3, :3], atol=1e-12)
    assert np.allclose(g.invert(pose) @ pose, np.eye(4), atol=1e-9)
    axis_angle = g.so3_log(pose[:3, :3])
    assert np.allclose(g.so3_exp(axis_angle), pose[:3, :3], atol=1e-9)


def test_quaternion_of_half_turns() -> None:
    for rotation in (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])):
        assert np.allclose(g.quaternion_to_rotation(g.rotation_to_quaternion(rotation)), rotation)


@settings(max_examples=50)
@given(st.integers(0, 2**32 - 1), fractions)
def test_slerp_moves_by_the_fraction_of_the_angle(seed: int, fraction: float) -> None:
    rng = np.random.default_rng(seed)
    a, b = random_pose(rng), random_pose(rng)
    total = g.rotation_angle(a[:3, :3].T @ b[:3, :3])
    mid = g.interpolate_pose(a, b, fraction)
    assert abs(g.rotation_angle(a[:3, :3].T @ mid[:3, :3]) - fraction * total) < 1e-6
    assert np.allclose(mid[:3, 3], a[:3, 3] + fraction * (b[:3, 3] - a[:3, 3]))


def test_slerp_endpoints() -> None:
    rng = np.random.default_rng(3)
    a, b = random_pose(rng), random_pose(rng)
    assert np.allclose(g.interpolate_pose(a, b, 0.0), a, atol=1e-9)
    assert np.allclose(g.interpolate_pose(a, b, 1.0), b, atol=1e-9)


@given(st.integers(0, 2**32 - 1))
def test_frame_conventions_round_trip_and_commute_with_transforms(seed: int) -> None:
    rng = np.random.default_rng(seed)
    native_pose = random_pose(rng)
    points = rng.normal(size=(20, 3)) * 100
    for conv in g.CONVENTIONS.values():
        canonical_pose = conv.pose_to_canonical(native_pose)
        assert np.allclose(conv.pose_to_native(canonical_pose), native_pose, atol=1e-9)
        assert np.allclose(conv.points_to_native(conv.points_to_canonical(points)), points)
        assert abs(np.linalg.det(canonical_pose[:3, :3]) - 1.0) < 1e-9
        # Transforming then converting equals converting then transforming in the canonical frame.
        lhs = conv.points_to_canonical(g.transform_points(native_pose, points))
        rhs = g.transform_points(canonical_pose, conv.points_to_canonical(points))
        assert np.allclose(lhs, rhs, atol=1e-9)


def test_uos_frame_is_left_handed_centimetres_y_up() -> None:
    # uos (x right, y up, z forward) in cm -> canonical (x forward, y left, z up) in m.
    point = g.UOS.points_to_canonical(np.array([[100.0, 200.0, 300.0]]))
    assert np.allclose(point, [[3.0, -1.0, 2.0]])
    assert np.linalg.det(g.UOS.axes_matrix) < 0  # a reflection: handedness changes


def test_pose_difference() -> None:
    a = g.pose_from_xyzrpy(1, 2, 3, 0.0, 0.0, 0.1)
    b = g.pose_from_xyzrpy(1, 2, 3.5, 0.0, 0.0, 0.0)
    dt, dr = g.pose_difference(a, b)
    assert abs(dt - 0.5) < 1e-12 and abs(dr - 0.1) < 1e-12


@settings(max_examples=50)
@given(st.floats(0.0, np.pi), st.integers(0, 2**32 - 1))
def test_rotation_angle_is_the_axis_angle_magnitude(angle: float, seed: int) -> None:
    axis = np.random.default_rng(seed).normal(size=3)
    axis /= np.linalg.norm(axis)
    assert abs(g.rotation_angle(g.so3_exp(angle * axis)) - angle) < 1e-9


def test_rotation_angle_ignores_the_rounding_of_rotations_read_from_text() -> None:
    """Poses stored with 7 significant digits are not exactly orthonormal; a metre-scale RPE must
    not read that as a rotation (arccos of the trace alone made it ~0.03°)."""
    rng = np.random.default_rng(0)
    rotation = g.so3_exp(rng.normal(size=3))
    rounded = np.round(rotation, 7)
    assert np.degrees(g.rotation_angle(rotation.T @ rounded)) < 1e-4
    small = g.so3_exp(np.array([0.0, 0.0, np.radians(0.01)]))
    assert abs(np.degrees(g.rotation_angle(rotation.T @ np.round(rotation @ small, 7))) - 0.01) < 1e-4


@given(st.integers(0, 10_000), st.integers(1, 500))
@settings(max_examples=30, deadline=None)
def test_cross_rows_is_numpys_cross_to_the_bit(seed: int, rows: int) -> None:
    """ICP's Jacobian is built with it: swapping it for np.cross must not move a pose by one ulp."""
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(rows, 3)) * 100, rng.normal(size=(rows, 3))
    expected = np.cross(a, b)
    assert np.array_equal(g.cross_rows(a, b), expected)
    jacobian = np.full((rows, 6), np.nan)
    assert g.cross_rows(a, b, out=jacobian[:, :3]) is not None
    assert np.array_equal(jacobian[:, :3], expected) and np.isnan(jacobian[:, 3:]).all()


def test_make_pose_of_stacks_is_each_pose_made_alone() -> None:
    """A relaxation round moves every free scan at once: a stack of rotations and translations gives
    the poses one call per scan would, and one of each gives a single 4x4 pose."""
    rng = np.random.default_rng(3)
    rotations = g.so3_exp(rng.normal(size=(5, 3)))
    translations = rng.normal(size=(5, 3))
    stacked = g.make_pose(rotations, translations)
    assert stacked.shape == (5, 4, 4)
    for pose, rotation, translation in zip(stacked, rotations, translations, strict=True):
        np.testing.assert_array_equal(pose, g.make_pose(rotation, translation))
    single = g.make_pose(rotations[0], translations[0].reshape(3, 1))
    assert single.shape == (4, 4) and single[3].tolist() == [0.0, 0.0, 0.0, 1.0]
