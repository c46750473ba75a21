"""How a simulated platform moves between scans, and the odometry it reports.

* ``robot`` - the seed's stop-and-go ground robot: the scans' stops are spread evenly over one lap
  of the route (``--scans`` sets how dense), the scanner 0.5 m above the ground, level with it.
* ``handheld`` - a person walking with a scanner at 1.4 m: steps of 0.3-0.7 m, looking around (a
  heading offset that wanders, ~12°, with turns capped at 45° between scans), and the wobble of a
  hand (roll and pitch ~4°, a few centimetres of sway).
* ``car`` - a roof-mounted lidar at 1.9 m: 1-3 m between scans with a speed that changes smoothly,
  the heading of the lane, and a little suspension pitch and roll.

The continuous motions (handheld, car) walk ``--scans`` steps along the route, lapping it if it is
shorter, so a session's extent grows with its length; the robot's stops cover one lap.

The odometry integrates planar motion with a distance scale error, a heading drift that grows with
distance and with turning (skid steering), small noise, a random walk in height and inclinometer
noise on roll/pitch - what a ``.pose`` file of a real ground robot carries, and what the pipeline
starts from.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import one_of
from slam6d.geometry import Matrix, make_pose, pose_from_xyzrpy, rot_x, rot_y, rot_z, xyzrpy_from_pose
from slam6d.scene_mesh import Scene
from slam6d.simulation_config import SimulationConfig


@dataclass(frozen=True)
class Motion:
    """Step lengths, turn behaviour and unsteadiness of one kind of platform."""

    name: str
    description: str
    sensor_height: float  # metres above the ground
    step_m: tuple[float, float] | None  # shortest and longest step; None: stops spread evenly over one lap
    speed_change_m: float  # std dev of the change of step length from one scan to the next (0: independent)
    look_deg: float  # std dev of the wandering offset of the heading from the route's
    max_turn_deg: float  # the largest heading change between consecutive scans the offset may add up to
    wobble_deg: float  # std dev of roll and pitch about the level (or ground-normal) attitude
    sway_m: float  # std dev of sideways and vertical displacement


MOTIONS: dict[str, Motion] = {
    motion.name: motion
    for motion in (
        Motion("robot", "stop-and-go ground robot, stops spread evenly over one lap", 0.5, None, 0.0, 0.0, 180.0, 0.0, 0.0),
        Motion("handheld", "walking, 0.3-0.7 m steps, looking round (turns up to 45°), hand wobble", 1.4, (0.3, 0.7),
               0.0, 12.0, 45.0, 4.0, 0.03),
        Motion("car", "driving, 1-3 m steps with smoothly varying speed, smooth yaw", 1.9, (1.0, 3.0), 0.3, 0.0, 180.0,
               0.2, 0.0),
    )
}  # fmt: skip
MOTION_NAMES = tuple(MOTIONS)


def get_motion(name: str) -> Motion:
    return one_of(MOTIONS, name, "motion")


def standing_pose(ground: NDArray[np.float64], heading: float, up: NDArray[np.float64], height: float) -> Matrix:
    """A scanner ``height`` above ``ground`` along ``up``, facing ``heading`` as far as ``up`` allows."""
    forward = np.array([np.cos(heading), np.sin(heading), 0.0])
    forward -= forward.dot(up) * up
    forward /= np.linalg.norm(forward)
    left = np.cross(up, forward)
    return make_pose(np.c_[forward, left, up], ground + height * up)


def stops(
    motion: Motion, scans: int, route_length: float, closing_gap: float, rng: np.random.Generator | None
) -> NDArray[np.float64]:
    """Arc lengths along the route at which the scans are taken (beyond one lap for long sessions)."""
    if motion.step_m is None:
        return np.linspace(0.0, route_length - closing_gap, scans)
    assert rng is not None, "steps of varying length are drawn from the session's generator"
    shortest, longest = motion.step_m
    if motion.speed_change_m == 0.0:
        steps = rng.uniform(shortest, longest, scans - 1)
    else:
        steps = np.empty(scans - 1)
        step = rng.uniform(shortest, longest)
        for k in range(scans - 1):
            step = float(np.clip(step + rng.normal(0.0, motion.speed_change_m), shortest, longest))
            steps[k] = step
    return np.r_[0.0, np.cumsum(steps)]


def _wrap(angle: float) -> float:
    return float(np.angle(np.exp(1j * angle)))


def ground_truth_poses(config: SimulationConfig, scene: Scene, rng: np.random.Generator | None = None) -> list[Matrix]:
    """Scanner poses standing on the route: up along the ground's normal, forward along the route,
    with the motion's steps, looking round and wobble. The robot draws nothing from ``rng``.

    ``config`` is resolved (:func:`slam6d.simulate.resolved`): its motion is named."""
    motion = get_motion(config.motion or "")
    height = config.sensor_height if config.sensor_height is not None else motion.sensor_height
    needs_draws = motion.step_m is not None or motion.look_deg or motion.wobble_deg or motion.sway_m
    if needs_draws and rng is None:
        raise ValueError(f"the {motion.name} motion draws from the session's generator: pass rng")
    route, terrain = scene.route, scene.terrain
    places = [
        route.stand(float(s) % route.length, terrain)
        for s in stops(motion, config.scans, route.length, config.closing_gap, rng)
    ]
    headings = [heading for _, heading, _ in places]
    if motion.look_deg:
        assert rng is not None
        offset, limit = 0.0, np.radians(motion.max_turn_deg)
        for k in range(len(headings)):
            offset = 0.6 * offset + rng.normal(0.0, np.radians(motion.look_deg))
            wanted = places[k][1] + offset
            if k > 0:
                wanted = headings[k - 1] + float(np.clip(_wrap(wanted - headings[k - 1]), -limit, limit))
                offset = _wrap(wanted - places[k][1])
            headings[k] = wanted
    poses = []
    for (ground, _, up), heading in zip(places, headings, strict=True):
        pose = standing_pose(ground, heading, up, height)
        if motion.wobble_deg or motion.sway_m:
            assert rng is not None
            roll, pitch = np.radians(
                np.clip(rng.normal(0.0, motion.wobble_deg, 2), -3 * motion.wobble_deg, 3 * motion.wobble_deg)
            )
            side, lift = rng.normal(0.0, motion.sway_m, 2)
            pose[:3, 3] += side * pose[:3, 1] + lift * pose[:3, 2]
            pose[:3, :3] = pose[:3, :3] @ rot_x(roll) @ rot_y(pitch)
        poses.append(pose)
    return poses


def drifting_odometry(config: SimulationConfig, truth: list[Matrix], rng: np.random.Generator) -> list[Matrix]:
    """Dead reckoning from the true motion: planar steps with scale and heading errors accumulate."""
    states = [xyzrpy_from_pose(p) for p in truth]
    x, y, z, _, _, yaw = states[0]
    odometry = [truth[0].copy()]
    tilt_noise = np.radians(config.odometry_tilt_noise_deg)
    for (px, py, pz, _, _, pyaw), (cx, cy, cz, roll, pitch, cyaw) in pairwise(states):
        step = rot_z(-pyaw)[:2, :2] @ np.array([cx - px, cy - py])
        distance = float(np.linalg.norm(step))
        turn = float(np.angle(np.exp(1j * (cyaw - pyaw))))
        measured = step * (1.0 + config.odometry_scale_error)
        measured += rng.normal(0.0, config.odometry_translation_noise * distance + 1e-12, 2)
        measured_turn = turn * (1.0 + config.odometry_turn_error) + np.radians(
            config.odometry_yaw_drift_deg_per_m * distance + rng.normal(0.0, config.odometry_yaw_noise_deg)
        )
        x, y = np.array([x, y]) + rot_z(yaw)[:2, :2] @ measured
        yaw += measured_turn
        z += (cz - pz) + rng.normal(0.0, config.odometry_height_noise)
        noisy_roll, noisy_pitch = roll + rng.normal(0.0, tilt_noise), pitch + rng.normal(0.0, tilt_noise)
        odometry.append(pose_from_xyzrpy(float(x), float(y), float(z), noisy_roll, noisy_pitch, float(yaw)))
    return odometry
