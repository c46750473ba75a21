"""Rigid-body geometry shared by every engine module.

Poses are 4x4 homogeneous matrices (``world_from_scan``: ``p_world = R @ p + t``) in the
canonical frame: right-handed, metres, z up. Keeping one representation everywhere means the
frame and unit quirks of file formats are handled once, at the edges (see :class:`FrameConvention`).
Angles are radians unless a name says ``deg``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam6d.errors import InvalidValueError

Matrix = NDArray[np.float64]

# Bounds of what a pose or a camera may hold. 10,000 km is beyond any map a scanner makes, yet far
# from where float64 arithmetic (squared distances, spline coefficients) overflows or loses metres.
MAX_COORDINATE_M = 1e7
# How far R^T R may stray from I (and det R from +1): rotations written to text files with 6
# significant digits stray by ~1e-6; a scaled, sheared or garbage matrix by far more.
RIGID_TOLERANCE = 1e-4


def make_pose(rotation: ArrayLike, translation: ArrayLike) -> Matrix:
    """Assemble a 4x4 pose from a 3x3 rotation and a 3-vector, or a stack of poses (n, 4, 4) from
    stacks of them ((n, 3, 3) and (n, 3)): a relaxation round moves every free scan at once."""
    rotation = np.asarray(rotation, dtype=np.float64)
    stack = rotation.shape[:-2]
    pose = np.zeros((*stack, 4, 4))
    pose[..., :3, :3] = rotation
    pose[..., :3, 3] = np.asarray(translation, dtype=np.float64).reshape(*stack, 3)
    pose[..., 3, 3] = 1.0
    return pose


def nearest_rotation(matrix: ArrayLike) -> Matrix:
    """The rotation closest to a 3x3 ``matrix``, or to each of a stack of them (the orthogonal polar
    factor, from the SVD).

    Poses are composed again and again (a loop's correction is applied to every later scan, the
    next loop's correction is computed from those poses, :func:`invert` transposes), so rounding
    that leaves a rotation a little off orthonormal is carried into every later product instead of
    being averaged out; whatever composes corrections in a chain puts its results back on SO(3)."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    sign = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= np.where(sign == 0, 1.0, sign)[..., None]  # no reflection
    return np.asarray(u @ vt)


def invert(pose: Matrix) -> Matrix:
    """Inverse of a rigid transform, exact (transpose) rather than a general matrix inverse."""
    rotation = pose[:3, :3].T
    return make_pose(rotation, -rotation @ pose[:3, 3])


def transform_points(pose: Matrix, points: Matrix) -> Matrix:
    """Apply a pose to an (N, 3) array of points."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def rot_x(angle: float) -> Matrix:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> Matrix:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> Matrix:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_to_rotation(rx: float, ry: float, rz: float) -> Matrix:
    """Rotation R = Rx(rx)·Ry(ry)·Rz(rz), the order 3DTK uses for ``.pose`` files."""
    return rot_x(rx) @ rot_y(ry) @ rot_z(rz)


def rotation_to_euler(rotation: Matrix) -> tuple[float, float, float]:
    """Angles (rx, ry, rz) with R = Rx·Ry·Rz; ry in [-pi/2, pi/2].

    At gimbal lock (|ry| = pi/2) rz is set to 0 and rx absorbs the rotation, so the
    round trip through :func:`euler_to_rotation` still reproduces the matrix.
    """
    sin_ry = float(np.clip(rotation[0, 2], -1.0, 1.0))
    ry = float(np.arcsin(sin_ry))
    if abs(sin_ry) < 1.0 - 1e-12:
        rx = float(np.arctan2(-rotation[1, 2], rotation[2, 2]))
        rz = float(np.arctan2(-rotation[0, 1], rotation[0, 0]))
    else:
        rz = 0.0
        rx = float(np.arctan2(rotation[2, 1], rotation[1, 1]))
    return rx, ry, rz


def pose_from_euler(translation: Matrix, rx: float, ry: float, rz: float) -> Matrix:
    return make_pose(euler_to_rotation(rx, ry, rz), translation)


def pose_from_xyzrpy(x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> Matrix:
    """Robot-style 6-tuple in the canonical frame: roll about x, pitch about y, yaw about z (up).

    The composition is yaw·pitch·roll (Rz·Ry·Rx), the aerospace convention robotics users expect
    when they type roll/pitch/yaw; it is distinct from the 3DTK file order on purpose.
    """
    return make_pose(rot_z(yaw) @ rot_y(pitch) @ rot_x(roll), np.array([x, y, z]))


def xyzrpy_from_pose(pose: Matrix) -> tuple[float, float, float, float, float, float]:
    """Inverse of :func:`pose_from_xyzrpy`."""
    r = pose[:3, :3]
    pitch = float(np.arcsin(np.clip(-r[2, 0], -1.0, 1.0)))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        roll = float(np.arctan2(r[2, 1], r[2, 2]))
        yaw = float(np.arctan2(r[1, 0], r[0, 0]))
    else:
        roll = float(np.arctan2(-r[1, 2], r[1, 1]))
        yaw = 0.0
    x, y, z = (float(v) for v in pose[:3, 3])
    return x, y, z, roll, pitch, yaw


# ---------------------------------------------------------------- quaternions (w, x, y, z)


def rotation_to_quaternion(rotation: Matrix) -> Matrix:
    """Unit quaternion (w, x, y, z) with w >= 0, robust for every rotation (Shepperd's method)."""
    r = rotation
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0.0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s])
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = np.array([(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s])
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = np.array([(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = np.array([(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0.0 else -q


def quaternion_to_rotation(q: ArrayLike) -> Matrix:
    """Rotation matrix of a quaternion (w, x, y, z); the quaternion need not be normalised."""
    quaternion = np.asarray(q, dtype=np.float64)
    w, x, y, z = quaternion / np.linalg.norm(quaternion)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def slerp(q0: Matrix, q1: Matrix, fraction: float) -> Matrix:
    """Spherical linear interpolation along the shorter arc, so loop corrections never go the long way round."""
    q0 = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: linear interpolation is exact to float precision
        q = q0 + fraction * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1.0 - fraction) * theta) * q0 + np.sin(fraction * theta) * q1) / np.sin(theta)


def interpolate_pose(start: Matrix, end: Matrix, fraction: float) -> Matrix:
    """Pose a given fraction of the way from ``start`` to ``end``: translation linear, rotation by slerp."""
    q = slerp(rotation_to_quaternion(start[:3, :3]), rotation_to_quaternion(end[:3, :3]), fraction)
    t = (1.0 - fraction) * start[:3, 3] + fraction * end[:3, 3]
    return make_pose(quaternion_to_rotation(q), t)


def rotation_angle(rotation: Matrix) -> float:
    """Angle of a rotation matrix in radians (0..pi).

    From both the cosine (trace) and the sine (skew part): arccos of the trace alone turns the
    1e-7 rounding of rotations read from text files into ~0.03° near the identity, which is as
    large as the errors that trajectory metrics are meant to resolve.
    """
    cos = (np.trace(rotation) - 1.0) / 2.0
    skew = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    return float(np.arctan2(np.linalg.norm(skew) / 2.0, cos))


def pose_difference(a: Matrix, b: Matrix) -> tuple[float, float]:
    """Translation distance and rotation angle (radians) between two poses: the error of ``a`` vs ``b``."""
    delta = invert(b) @ a
    return float(np.linalg.norm(delta[:3, 3])), rotation_angle(delta[:3, :3])


def cross_rows(
    a: NDArray[np.float64], b: NDArray[np.float64], out: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Row-wise cross products of two (N, 3) arrays, into ``out`` (N, 3) when given.

    The same products and differences as ``np.cross`` (equal to the bit), without its axis
    handling, which is most of its cost on the few thousand rows of an ICP step: ~0.18 against
    ~0.1 ms for 5,000 rows, paid once per ICP iteration (1,400 on a 30-scan walk)."""
    out = np.empty((len(a), 3)) if out is None else out
    np.subtract(a[:, 1] * b[:, 2], a[:, 2] * b[:, 1], out=out[:, 0])
    np.subtract(a[:, 2] * b[:, 0], a[:, 0] * b[:, 2], out=out[:, 1])
    np.subtract(a[:, 0] * b[:, 1], a[:, 1] * b[:, 0], out=out[:, 2])
    return out


def skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cross-product matrices [v]x of a stack of vectors (..., 3) -> (..., 3, 3)."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrices of rotation vectors (axis times angle), one (3,) or a stack (..., 3), by
    Rodrigues' formula: the exponential map of SO(3), as small-angle updates of ICP and the pose
    graph need it."""
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    k = skew(phi)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def so3_log(rotation: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vectors of a stack of rotations (..., 3, 3) -> (..., 3), stable near 0 and near pi.

    The angle comes from both its cosine and its sine, as in :func:`rotation_angle`: the vector's
    length is the angle divided by sin(angle), so an error of arccos near pi (1e-13) grows to 1e-10.
    """
    cos = (np.trace(rotation, axis1=-2, axis2=-1) - 1.0) / 2.0
    vee = np.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        axis=-1,
    )
    theta = np.arctan2(np.linalg.norm(vee, axis=-1) / 2.0, cos)
    small = theta < 1e-6
    sin = np.sin(theta)
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, sin)))
    out = vee * scale[..., None]
    near_pi = theta > np.pi - 1e-3
    if np.any(near_pi):  # the antisymmetric part vanishes there: take the axis from the quaternion
        for index in np.argwhere(near_pi.reshape(-1)).ravel():
            q = rotation_to_quaternion(rotation.reshape(-1, 3, 3)[index])
            sin_half = float(np.linalg.norm(q[1:]))
            out.reshape(-1, 3)[index] = q[1:] / sin_half * 2.0 * np.arctan2(sin_half, q[0])
    return out


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> Matrix:
    """world_from_camera pose at ``eye`` looking at ``target`` with ``up`` appearing up in the image.

    Camera axes are OpenCV's (x right, y down, z forward), as the renderer and viser use.

    When the viewing direction is (anti)parallel to ``up`` the roll is undefined; another axis is
    borrowed so the result is still a proper rotation rather than NaN.
    """
    eye_v = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye_v
    norm = float(np.linalg.norm(forward))
    if norm < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward /= norm
    up_v = np.asarray(up, dtype=np.float64)
    right = np.cross(forward, up_v)
    if np.linalg.norm(right) < 1e-9 * max(float(np.linalg.norm(up_v)), 1e-300):
        helper = np.array([1.0, 0.0, 0.0]) if abs(forward[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        right = np.cross(forward, helper)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return make_pose(np.stack([right, down, forward], axis=1), eye_v)


# ---------------------------------------------------------------- checking values from outside


def check_rigid(
    pose: ArrayLike, field: str = "pose", tolerance: float = RIGID_TOLERANCE, max_coordinate: float = MAX_COORDINATE_M
) -> Matrix:
    """``pose`` as a 4x4 float64 matrix, or :class:`InvalidValueError` naming ``field`` and what is wrong.

    A pose is rigid when its rotation is orthonormal with determinant +1 (within ``tolerance``), its
    bottom row is 0 0 0 1, and every entry is finite with a translation within ``max_coordinate``.
    Anything else - zero, scaled, sheared, reflected, a garbage bottom row, 1e308 - would be stored
    and then silently break every consumer (exports write other rotations, solvers raise), so the
    engine refuses it where it enters instead.
    """
    try:
        matrix = np.array(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidValueError(field, "must be a 4x4 matrix of numbers") from None
    if matrix.shape != (4, 4):
        raise InvalidValueError(field, f"must be a 4x4 matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise InvalidValueError(field, "must hold finite numbers only (no NaN or infinity)")
    if np.abs(matrix[3] - (0.0, 0.0, 0.0, 1.0)).max() > tolerance:
        raise InvalidValueError(field, f"bottom row must be 0 0 0 1, got {_numbers(matrix[3])}")
    translation = matrix[:3, 3]
    if np.abs(translation).max() > max_coordinate:
        raise InvalidValueError(field, f"translation {_numbers(translation)} is beyond ±{max_coordinate:g} m")
    rotation = matrix[:3, :3]
    if np.abs(rotation).max() > 2.0:  # clearly garbage; also keeps RᵀR below overflow
        raise InvalidValueError(field, "rotation entries must lie within [-1, 1] (a scaled or garbage matrix)")
    deviation = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if deviation > tolerance:
        raise InvalidValueError(
            field, f"rotation is not orthonormal (|RᵀR - I| = {deviation:.2g}; scaled, sheared or not a rotation)"
        )
    determinant = float(np.linalg.det(rotation))
    if abs(determinant - 1.0) > tolerance:
        raise InvalidValueError(field, f"rotation has determinant {determinant:.3g}, must be +1 (not a reflection)")
    matrix[3] = (0.0, 0.0, 0.0, 1.0)
    return matrix


def check_quaternion(q: ArrayLike, field: str = "orientation_wxyz", max_component: float = 1e6) -> Matrix:
    """A unit quaternion (w, x, y, z) from ``q``, normalised, or :class:`InvalidValueError` naming ``field``.

    Any finite, non-zero quaternion of reasonable size is accepted and normalised (clients send
    rounded or unnormalised ones); zero, non-finite or huge components (1e200 squares to infinity
    in the next formula that touches it) are refused.
    """
    try:
        quaternion = np.array(q, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidValueError(field, "must be 4 numbers (w, x, y, z)") from None
    if quaternion.shape != (4,):
        raise InvalidValueError(field, f"must be 4 numbers (w, x, y, z), got shape {quaternion.shape}")
    if not np.isfinite(quaternion).all():
        raise InvalidValueError(field, "must hold finite numbers only")
    if np.abs(quaternion).max() > max_component:
        raise InvalidValueError(field, f"components must lie within ±{max_component:g}")
    norm = float(np.linalg.norm(quaternion))
    if norm < 1e-6:
        raise InvalidValueError(field, "is zero (or nearly): it names no rotation")
    return quaternion / norm


def check_point(point: ArrayLike, field: str = "position", max_coordinate: float = MAX_COORDINATE_M) -> Matrix:
    """A finite 3-vector within ``max_coordinate`` metres, or :class:`InvalidValueError` naming ``field``."""
    try:
        vector = np.array(point, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidValueError(field, "must be 3 numbers") from None
    if vector.shape != (3,):
        raise InvalidValueError(field, f"must be 3 numbers, got shape {vector.shape}")
    if not np.isfinite(vector).all():
        raise InvalidValueError(field, "must hold finite numbers only")
    if np.abs(vector).max() > max_coordinate:
        raise InvalidValueError(field, f"{_numbers(vector)} is beyond ±{max_coordinate:g} m")
    return vector


def _numbers(values: NDArray[np.float64]) -> str:
    return " ".join(f"{float(v):.6g}" for v in values)


# ---------------------------------------------------------------- frame conventions


@dataclass(frozen=True)
class FrameConvention:
    """How a file format's coordinates relate to the canonical frame (right-handed, metres, z up).

    ``axes`` maps native axis directions to canonical ones and may be a reflection (det -1): that is
    how a left-handed frame becomes right-handed. ``metres_per_unit`` scales lengths. Points convert
    as ``p_c = metres_per_unit * axes @ p_n``; poses conjugate by ``axes`` so that rotations stay
    proper in both frames.
    """

    name: str
    metres_per_unit: float
    axes: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    @property
    def axes_matrix(self) -> Matrix:
        return np.array(self.axes, dtype=np.float64)

    def points_to_canonical(self, points: Matrix) -> Matrix:
        return (np.asarray(points, dtype=np.float64) @ self.axes_matrix.T) * self.metres_per_unit

    def points_to_native(self, points: Matrix) -> Matrix:
        return (np.asarray(points, dtype=np.float64) / self.metres_per_unit) @ self.axes_matrix

    def similarity_to_canonical(self) -> Matrix:
        """4x4 matrix taking native homogeneous points to canonical ones (scale and axes, no translation)."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.metres_per_unit * self.axes_matrix
        return matrix

    def information_to_native(self, information: Matrix) -> Matrix:
        """A relative pose's 6x6 information (translation, rotation) in this frame instead of the canonical one.

        Native relative poses are the canonical ones conjugated by the similarity, so a canonical
        tangent (t, r) maps to (axesᵀ t / s, det(axes) axesᵀ r); information transforms by the inverse
        of that map, on both sides.
        """
        axes = self.axes_matrix
        back = np.zeros((6, 6))
        back[:3, :3] = self.metres_per_unit * axes
        back[3:, 3:] = np.linalg.det(axes) * axes
        return back.T @ np.asarray(information, dtype=np.float64) @ back

    def similarity_from_canonical(self) -> Matrix:
        matrix = np.eye(4)
        matrix[:3, :3] = self.axes_matrix.T / self.metres_per_unit
        return matrix

    def pose_to_canonical(self, pose: Matrix) -> Matrix:
        a = self.axes_matrix
        return make_pose(a @ pose[:3, :3] @ a.T, self.metres_per_unit * (a @ pose[:3, 3]))

    def pose_to_native(self, pose: Matrix) -> Matrix:
        a = self.axes_matrix
        return make_pose(a.T @ pose[:3, :3] @ a, (a.T @ pose[:3, 3]) / self.metres_per_unit)


CANONICAL = FrameConvention("canonical", 1.0)

# 3DTK "uos": centimetres, left-handed, x right, y up, z forward. Canonical x = forward (z_uos),
# y = left (-x_uos), z = up (y_uos): the same mapping 3DTK uses when it exports to ROS.
UOS = FrameConvention("uos", 0.01, ((0.0, 0.0, 1.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)))

# Right-handed, metres, y up (PLY scans such as the Stanford bunny): canonical z = y_native.
Y_UP = FrameConvention("y_up", 1.0, ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)))

CONVENTIONS: dict[str, FrameConvention] = {c.name: c for c in (CANONICAL, UOS, Y_UP)}


def uos_pose(translation_cm: Matrix, angles_deg: Matrix) -> Matrix:
    """Native 3DTK pose from a ``.pose`` file's two lines (cm, degrees, R = Rx·Ry·Rz)."""
    rx, ry, rz = np.radians(np.asarray(angles_deg, dtype=np.float64))
    return pose_from_euler(np.asarray(translation_cm, dtype=np.float64), rx, ry, rz)


def path_lengths(poses: Sequence[Matrix]) -> NDArray[np.float64]:
    """Cumulative distance travelled along the trajectory, one value per scan (0 at scan 0)."""
    positions = np.array([p[:3, 3] for p in poses])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])
