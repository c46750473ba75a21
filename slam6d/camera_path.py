"""Camera paths for fly-through videos: keyframes in, a smooth evenly paced sequence of cameras out.

A path is a list of keyframes (position, orientation, field of view) through which positions run
on a C2 cubic spline and orientations on a rotation spline. Frames are spaced by *distance* along
the path (metres at ``speed`` per second of video), or by turning angle where the camera mostly
turns on the spot, so a path never rushes through long segments and crawls through short ones.

The default path follows the robot: keyframes ``height`` metres above the scan positions, and the
camera looks at the point ``look_ahead`` metres further along the smoothed trajectory instead of
using keyframe orientations, as in the fly-through of the original Kurt3D maps.

Orientations use the renderer's camera axes (OpenCV: x right, y down, z forward), which are also
viser's, so a keyframe taken from the browser's current view needs no conversion. Quaternions are
(w, x, y, z) like everywhere else in the engine.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from slam6d.errors import FormatError, InvalidValueError, Slam6dError
from slam6d.geometry import (
    Matrix,
    check_point,
    check_quaternion,
    look_at,
    make_pose,
    quaternion_to_rotation,
    rotation_to_quaternion,
)

PATH_FORMAT = "slam6d-camera-path"
PATH_VERSION = 1
_DENSE_PER_SEGMENT = 64  # spline samples per keyframe segment used to measure distance and turning


@dataclass
class Keyframe:
    """One view: camera position, world_from_camera rotation as (w, x, y, z), vertical field of view."""

    position: NDArray[np.float64]
    orientation: NDArray[np.float64]
    fov_deg: float = 60.0

    def __post_init__(self) -> None:
        self.position = check_point(self.position, "position")
        self.orientation = check_quaternion(self.orientation, "orientation_wxyz")
        self.fov_deg = check_fov(self.fov_deg)

    @classmethod
    def from_pose(cls, pose: Matrix, fov_deg: float = 60.0) -> Keyframe:
        return cls(pose[:3, 3], rotation_to_quaternion(pose[:3, :3]), fov_deg)

    @classmethod
    def looking_at(cls, eye: ArrayLike, target: ArrayLike, fov_deg: float = 60.0) -> Keyframe:
        return cls.from_pose(look_at(eye, target), fov_deg)

    def pose(self) -> Matrix:
        return make_pose(quaternion_to_rotation(self.orientation), self.position)


@dataclass
class CameraPath:
    """Keyframes plus pacing. With ``look_ahead`` (metres) set, the camera looks along the path itself."""

    keyframes: list[Keyframe] = field(default_factory=list)
    speed: float = 1.0  # metres of path per second of video
    turn_speed_deg: float = 30.0  # degrees per second where turning takes longer than moving
    look_ahead: float | None = None
    pitch_deg: float = -10.0  # look-ahead mode: how far below the horizon the camera looks

    def __post_init__(self) -> None:
        if self.speed <= 0 or self.turn_speed_deg <= 0:
            raise ValueError("speed and turn_speed_deg must be positive")
        if self.look_ahead is not None and self.look_ahead <= 0:
            raise ValueError("look_ahead must be positive (or None to use keyframe orientations)")

    # -- editing, for the keyframe list a user builds in the browser

    def add(self, keyframe: Keyframe, index: int | None = None) -> None:
        self.keyframes.insert(len(self.keyframes) if index is None else index, keyframe)

    def remove(self, index: int) -> Keyframe:
        return self.keyframes.pop(index)

    def move(self, old_index: int, new_index: int) -> None:
        self.keyframes.insert(new_index, self.keyframes.pop(old_index))

    # -- sampling

    def duration(self) -> float:
        """Seconds of video the path lasts at its pacing."""
        return self._pacing()[1][-1] if len(self.keyframes) > 1 else 0.0

    def frame_count(self, fps: float) -> int:
        return max(1, round(self.duration() * fps) + 1)

    def sample(self, frames: int | None = None, fps: float = 30.0) -> list[tuple[Matrix, float]]:
        """(world_from_camera pose, vertical fov in degrees) for each frame, evenly paced.

        ``frames`` overrides the count the pacing implies (the path is then stretched or squeezed).
        """
        if not self.keyframes:
            raise Slam6dError("the camera path has no keyframes")
        count = self.frame_count(fps) if frames is None else int(frames)
        if count < 1:
            raise ValueError(f"frame count must be at least 1, got {count}")
        if len(self.keyframes) == 1:
            return [(self.keyframes[0].pose(), self.keyframes[0].fov_deg)] * count
        dense_t, cumulative = self._pacing()
        targets = np.linspace(0.0, cumulative[-1], count) if count > 1 else np.zeros(1)
        t = np.interp(targets, cumulative, dense_t)
        positions = self._position_spline()(t)
        fovs = np.interp(t, self._knots(), [k.fov_deg for k in self.keyframes])
        if self.look_ahead is None:
            rotations = self._rotation_spline()(t).as_matrix()
        else:
            rotations = self._look_ahead_rotations(positions, targets, dense_t, cumulative)
        return [(make_pose(r, p), float(f)) for r, p, f in zip(rotations, positions, fovs, strict=True)]

    def preview(self, points: int = 200) -> NDArray[np.float64]:
        """Positions along the path, for drawing it as a line before rendering."""
        if len(self.keyframes) < 2:
            return np.array([k.position for k in self.keyframes]).reshape(-1, 3)
        return np.array([pose[:3, 3] for pose, _ in self.sample(frames=points)])

    # -- internals

    def _knots(self) -> NDArray[np.float64]:
        """Spline parameter per keyframe: distance plus turning, so the parameter is roughly even in time."""
        knots = [0.0]
        for a, b in itertools.pairwise(self.keyframes):
            dist = float(np.linalg.norm(b.position - a.position)) / self.speed
            turn = _angle_between(a.orientation, b.orientation) / math.radians(self.turn_speed_deg)
            knots.append(knots[-1] + max(dist, turn, 1e-3))
        return np.array(knots)

    def _position_spline(self) -> CubicSpline:
        return CubicSpline(self._knots(), np.array([k.position for k in self.keyframes]), bc_type="natural")

    def _rotation_spline(self) -> RotationSpline:
        quats = np.array([k.orientation for k in self.keyframes])
        for i in range(1, len(quats)):  # same hemisphere as the previous one: the spline takes the short way
            if np.dot(quats[i], quats[i - 1]) < 0:
                quats[i] = -quats[i]
        return RotationSpline(self._knots(), Rotation.from_quat(quats[:, [1, 2, 3, 0]]))

    def _pacing(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Dense spline parameters and the video time (s) reached at each: distance/speed vs turning/turn speed."""
        knots = self._knots()
        dense_t = np.concatenate(
            [np.linspace(a, b, _DENSE_PER_SEGMENT, endpoint=False) for a, b in itertools.pairwise(knots)] + [knots[-1:]]
        )
        positions = self._position_spline()(dense_t)
        step = np.linalg.norm(np.diff(positions, axis=0), axis=1) / self.speed
        if self.look_ahead is None:
            rotations = self._rotation_spline()(dense_t)
            turn = (rotations[1:] * rotations[:-1].inv()).magnitude() / math.radians(self.turn_speed_deg)
            step = np.maximum(step, turn)
        cumulative = np.concatenate([[0.0], np.cumsum(step)])
        if cumulative[-1] <= 0.0:  # keyframes that neither move nor turn: spread frames over the parameter
            cumulative = dense_t - dense_t[0]
        return dense_t, _strictly_increasing(cumulative)

    def _look_ahead_rotations(
        self,
        positions: NDArray[np.float64],
        targets: NDArray[np.float64],
        dense_t: NDArray[np.float64],
        cumulative: NDArray[np.float64],
    ) -> list[Matrix]:
        """Look at the path point ``look_ahead`` metres on; past the end, along the end's direction."""
        assert self.look_ahead is not None
        spline = self._position_spline()
        ahead = self.look_ahead / self.speed  # in video seconds, the unit of ``cumulative``
        end_time = cumulative[-1]
        end = spline(dense_t[-1])
        end_direction = spline(dense_t[-1], 1)
        if np.linalg.norm(end_direction[:2]) < 1e-9:
            end_direction = end - spline(dense_t[-2])
        end_direction = end_direction / max(float(np.linalg.norm(end_direction)), 1e-12)
        drop = math.tan(math.radians(-self.pitch_deg)) * self.look_ahead
        rotations = []
        for position, time in zip(positions, targets, strict=True):
            goal_time = time + ahead
            if goal_time <= end_time:
                goal = spline(np.interp(goal_time, cumulative, dense_t))
            else:
                goal = end + end_direction * (goal_time - end_time) * self.speed
            goal = goal - np.array([0.0, 0.0, drop])
            rotations.append(look_at(position, goal)[:3, :3])
        return rotations

    # -- files

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": PATH_FORMAT,
            "version": PATH_VERSION,
            "speed": self.speed,
            "turn_speed_deg": self.turn_speed_deg,
            "look_ahead": self.look_ahead,
            "pitch_deg": self.pitch_deg,
            "keyframes": [keyframe_to_dict(k) for k in self.keyframes],
        }


def check_fov(value: Any, field: str = "fov_deg") -> float:
    """A vertical field of view in degrees within [1, 179), or :class:`InvalidValueError` naming ``field``."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise InvalidValueError(field, f"must be a number of degrees, got {type(value).__name__}")
    fov = float(value)
    if not 1.0 <= fov < 179.0:
        raise InvalidValueError(field, f"field of view must lie within [1, 179) degrees, got {fov:g}")
    return fov


def keyframe_from_dict(item: Any, field: str = "keyframe") -> Keyframe:
    """One keyframe of the JSON form (position, orientation_wxyz, fov_deg); errors name ``field``.

    Used for files and for keyframes a client stores in a session alike, so nothing that cannot be
    rendered (a zero or 1e200 quaternion, a NaN position) is ever kept.
    """
    if not isinstance(item, dict):
        raise InvalidValueError(field, "must be an object with position, orientation_wxyz and fov_deg")
    for key in ("position", "orientation_wxyz"):
        if key not in item:
            raise InvalidValueError(f"{field}.{key}", "is missing")
    return Keyframe(
        check_point(item["position"], f"{field}.position"),
        check_quaternion(item["orientation_wxyz"], f"{field}.orientation_wxyz"),
        check_fov(item.get("fov_deg", 60.0), f"{field}.fov_deg"),
    )


def keyframe_to_dict(keyframe: Keyframe) -> dict[str, Any]:
    return {
        "position": keyframe.position.tolist(),
        "orientation_wxyz": keyframe.orientation.tolist(),
        "fov_deg": keyframe.fov_deg,
    }


def _angle_between(q0: NDArray[np.float64], q1: NDArray[np.float64]) -> float:
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))


def _strictly_increasing(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """np.interp needs increasing x; flat stretches (no motion) get a negligible slope."""
    return values + np.arange(len(values)) * 1e-9 * max(float(values[-1]), 1.0)


def camera_path_from_dict(data: Any, source: Path | str = "camera path") -> CameraPath:
    """Parse the JSON form; errors name ``source`` and the offending field."""
    if not isinstance(data, dict):
        raise FormatError(source, "a camera path must be a JSON object")
    if data.get("format", PATH_FORMAT) != PATH_FORMAT:
        raise FormatError(source, f"not a camera path (format is {data.get('format')!r}, expected {PATH_FORMAT!r})")
    if int(data.get("version", PATH_VERSION)) > PATH_VERSION:
        raise FormatError(source, f"camera path version {data['version']} is newer than this program ({PATH_VERSION})")
    raw = data.get("keyframes")
    if not isinstance(raw, list) or not raw:
        raise FormatError(source, "'keyframes' must be a non-empty list")
    try:
        keyframes = [keyframe_from_dict(item, f"keyframes[{i}]") for i, item in enumerate(raw)]
    except InvalidValueError as exc:
        raise FormatError(source, str(exc)) from None
    try:
        return CameraPath(
            keyframes,
            speed=float(data.get("speed", 1.0)),
            turn_speed_deg=float(data.get("turn_speed_deg", 30.0)),
            look_ahead=None if data.get("look_ahead") is None else float(data["look_ahead"]),
            pitch_deg=float(data.get("pitch_deg", -10.0)),
        )
    except (TypeError, ValueError) as exc:
        raise FormatError(source, str(exc)) from None


def load_camera_path(path: Path | str) -> CameraPath:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise FormatError(path, f"cannot read camera path: {exc.strerror or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise FormatError(path, f"invalid JSON: {exc.msg}", line=exc.lineno) from None
    return camera_path_from_dict(data, path)


def save_camera_path(path: Path | str, camera_path: CameraPath) -> Path:
    """Write the JSON form atomically (a half-written path file would fail the next render)."""
    from slam6d.trace import write_trace

    path = Path(path)
    write_trace(path, camera_path.to_dict())
    return path


def trajectory_path(
    scan_poses: Sequence[Matrix],
    height: float = 1.0,
    speed: float = 1.0,
    look_ahead: float = 2.0,
    pitch_deg: float = -10.0,
    min_spacing: float = 0.5,
    fov_deg: float = 70.0,
    scene: object | None = None,
) -> CameraPath:
    """The default fly-through: ``height`` m above the scan positions, looking ahead along the way.

    Scan positions closer than ``min_spacing`` to the previous kept one are dropped, which removes
    the standing-still start of a recording and the jitter a spline would otherwise turn into
    wobble. A robot that never moved (or a single scan) gets a slow 360° look-around instead.
    ``scene`` is accepted so callers can pass the render scene; only its scan poses matter here.
    """
    poses = [np.asarray(p, dtype=np.float64) for p in scan_poses]
    if not poses and scene is not None:
        poses = list(getattr(scene, "scan_poses", []))
    if not poses:
        raise Slam6dError("cannot build a fly-through path: there are no scan positions")
    lift = np.array([0.0, 0.0, height])
    kept = [poses[0][:3, 3] + lift]
    for pose in poses[1:]:
        position = pose[:3, 3] + lift
        if np.linalg.norm(position - kept[-1]) >= min_spacing:
            kept.append(position)
    last = poses[-1][:3, 3] + lift
    if len(kept) > 1 and np.linalg.norm(last - kept[-1]) > 1e-9:
        kept[-1] = last  # end where the robot ended, even if the final step was short
    if len(kept) < 2:
        return _look_around(kept[0], poses[0], fov_deg, pitch_deg)
    keyframes = [
        Keyframe.looking_at(p, nxt - np.array([0.0, 0.0, math.tan(math.radians(-pitch_deg))]), fov_deg)
        for p, nxt in zip(kept, [*kept[1:], 2 * kept[-1] - kept[-2]], strict=True)
    ]
    return CameraPath(keyframes, speed=speed, look_ahead=look_ahead, pitch_deg=pitch_deg)


def _look_around(position: NDArray[np.float64], pose: Matrix, fov_deg: float, pitch_deg: float) -> CameraPath:
    """Turn once on the spot, starting along the scanner's heading (its x axis in the ground plane)."""
    heading = pose[:3, 0].copy()
    heading[2] = 0.0
    if np.linalg.norm(heading) < 1e-6:
        heading = np.array([1.0, 0.0, 0.0])
    yaw0 = math.atan2(heading[1], heading[0])
    drop = math.tan(math.radians(-pitch_deg))
    keyframes = []
    for k in range(9):  # 45° steps: a quarter turn between keyframes would let the spline cut corners
        yaw = yaw0 + k * math.pi / 4.0
        target = position + np.array([math.cos(yaw), math.sin(yaw), -drop])
        keyframes.append(Keyframe.looking_at(position, target, fov_deg))
    return CameraPath(keyframes, turn_speed_deg=30.0)
