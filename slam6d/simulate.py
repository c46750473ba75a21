"""Simulated sessions with exact ground truth: any of our sensors, worlds and motions.

Real data never comes with a perfect reference, so the pipeline's accuracy (ATE/RPE), its
robustness on other sensors and places, and the workbench's default session come from here. A
session is a sensor (:mod:`slam6d.sensors`: the seed's rotating or tilting SICK fan, or a VLP-16,
HDL-32E, HDL-64E or Ouster OS1-64) carried by a platform (:mod:`slam6d.motion`: a stop-and-go
robot, a person walking, a car) along the route of a world (:mod:`slam6d.worlds`: the seed's loop,
a building's floor, streets, a km-scale campus). The world is one triangle mesh cast against by
open3d's Embree ray caster (deterministic, about 10 ms per 100k rays), built once per session, so
scans cost little beyond writing them. Everything random is drawn from one seeded generator in a
fixed order: the same seed gives byte-identical files, and the default (loop, rotating SICK,
robot) draws exactly what the seed's simulator drew.

Ground truth and odometry are written as KITTI 3x4 files in the same native uos frame and units
(cm) as the ``.pose`` files, to compare directly with results. Without odometry
(``odometry=False``) no ``.pose`` files are written: the readers then take every scan at the
identity with ``has_pose`` False, which makes the pipeline search for its initial guesses.
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Slam6dError
from slam6d.geometry import UOS, Matrix
from slam6d.io.poses import write_kitti_poses
from slam6d.io.uos import write_uos_scan
from slam6d.motion import MOTION_NAMES, drifting_odometry, get_motion, ground_truth_poses
from slam6d.scene_mesh import Scene
from slam6d.sensors import POINTS_PER_LINE, SENSOR_NAMES, beam_directions, get_sensor
from slam6d.simulation_config import SimulationConfig
from slam6d.worlds import WORLD_NAMES, get_world

__all__ = [
    "MOTION_NAMES",
    "POINTS_PER_LINE",
    "SENSOR_NAMES",
    "WORLD_NAMES",
    "SimulatedSession",
    "Simulation",
    "SimulationConfig",
    "build_scene",
    "drifting_odometry",
    "ground_truth_poses",
    "resolved",
    "scan_pattern",
    "simulate_scan",
    "simulate_session",
    "simulated_scans",
    "validate",
]

Progress = Callable[[int, int], None]
_SCAN_FILE = re.compile(r"^scan\d{3,}\.")


def resolved(config: SimulationConfig) -> SimulationConfig:
    """``config`` with every None replaced by the world's, sensor's or motion's value.

    The worlds and motions take a resolved configuration: they build from the values, while the
    choice of defaults is made here, where the registries of worlds, sensors and motions meet.
    """
    world = get_world(config.world)
    sensor = get_sensor(config.sensor or world.sensor)
    motion = get_motion(config.motion or world.motion)
    return dataclasses.replace(
        config,
        sensor=sensor.name,
        motion=motion.name,
        points_per_scan=config.points_per_scan if config.points_per_scan is not None else sensor.native_shots,
        max_range=config.max_range if config.max_range is not None else sensor.max_range,
        range_noise=config.range_noise if config.range_noise is not None else sensor.range_noise,
        sensor_height=config.sensor_height if config.sensor_height is not None else motion.sensor_height,
    )


def validate(config: SimulationConfig) -> None:
    """Refuse a configuration no session can be drawn from (ValueError naming the field)."""
    if config.scans < 2:
        raise ValueError(f"a session needs at least 2 scans, got {config.scans}")
    full = resolved(config)  # names the unknown world, sensor or motion
    sensor = get_sensor(full.sensor or "")
    assert full.points_per_scan is not None and full.max_range is not None
    if full.points_per_scan < sensor.beams:
        what = "laser per column" if sensor.is_multi_beam else "scan line"
        raise ValueError(f"points_per_scan must be at least one {what} ({sensor.beams}) for {sensor.name}")
    if not config.elevation_min_deg < config.elevation_max_deg:
        raise ValueError("elevation_min_deg must be below elevation_max_deg")
    if not 0.0 < config.min_range < full.max_range:
        raise ValueError("need 0 < min_range < max_range")
    if full.range_noise is not None and full.range_noise < 0.0:
        raise ValueError("range_noise must not be negative")
    if min(config.loop_length, config.loop_width) < 8.0:
        raise ValueError("the loop must be at least 8 m in each direction")


def build_scene(config: SimulationConfig, rng: np.random.Generator) -> Scene:
    """The world of a session; drawn first from the seeded generator, so ``default_rng(seed)`` rebuilds it."""
    full = resolved(config)
    return get_world(full.world).build(full, rng)


@dataclass
class SimulatedSession:
    """What :func:`simulate_session` wrote; poses are canonical ``world_from_scan`` (metres).

    ``odometry`` is the simulated dead reckoning even when it was not written (``odometry_file``
    None): the same seed draws the same scans with or without it.
    """

    directory: Path
    scan_paths: list[Path]
    ground_truth: list[Matrix] = field(repr=False)
    odometry: list[Matrix] = field(repr=False)
    point_counts: list[int]
    ground_truth_file: Path
    odometry_file: Path | None
    parameters_file: Path
    path_length_m: float  # of the route the world offers (one lap)


def scan_pattern(config: SimulationConfig) -> NDArray[np.float64]:
    """Unit ray directions in the scanner frame (x forward, y left, z up), in firing order."""
    config = resolved(config)
    assert config.points_per_scan is not None
    return beam_directions(
        get_sensor(config.sensor or ""), config.points_per_scan, config.elevation_min_deg, config.elevation_max_deg
    )


def simulate_scan(
    config: SimulationConfig, scene: Scene, pose: Matrix, directions: NDArray[np.float64], rng: np.random.Generator
) -> NDArray[np.float64]:
    """Noisy returns of one scan in the scanner frame (canonical, metres), in firing order."""
    config = resolved(config)
    assert config.range_noise is not None and config.max_range is not None
    world_dirs = directions @ pose[:3, :3].T
    ranges = scene.cast(pose[:3, 3], world_dirs)
    ranges = ranges + rng.normal(0.0, config.range_noise, len(ranges))
    keep = np.isfinite(ranges) & (ranges >= config.min_range) & (ranges <= config.max_range)
    return directions[keep] * ranges[keep, None]


@dataclass
class Simulation:
    """A session drawn up to its scans: the world, the true and the odometry poses, the beams.

    :meth:`scans` casts the scans in order from the same generator, so it can be iterated once;
    holding one scan at a time keeps a long session's memory bounded by the scene.
    """

    config: SimulationConfig  # resolved
    scene: Scene
    truth: list[Matrix]
    odometry: list[Matrix]
    directions: NDArray[np.float64]
    rng: np.random.Generator

    def scans(self) -> Iterator[NDArray[np.float64]]:
        """Each scan's points in its scanner frame (canonical, metres), in firing order."""
        for pose in self.truth:
            yield simulate_scan(self.config, self.scene, pose, self.directions, self.rng)


def simulated_scans(config: SimulationConfig) -> Simulation:
    """Everything of a session but the files: its draws in the order :func:`simulate_session` makes them."""
    validate(config)
    config = resolved(config)
    rng = np.random.default_rng(config.seed)
    scene = build_scene(config, rng)
    truth = ground_truth_poses(config, scene, rng)
    odometry = drifting_odometry(config, truth, rng)  # drawn even when not written: the scans stay the same
    return Simulation(config, scene, truth, odometry, scan_pattern(config), rng)


def simulate_session(
    out_dir: Path | str,
    config: SimulationConfig | None = None,
    progress: Progress | None = None,
    overwrite: bool = False,
) -> SimulatedSession:
    """Write a uos session (``scanNNN.3d`` + odometry ``.pose``) with ground truth beside it.

    Scans already in ``out_dir`` are refused unless ``overwrite``: left-over higher-numbered scans
    of an earlier, longer session would otherwise silently join the new one. Without odometry no
    ``.pose`` files and no ``odometry_kitti.txt`` are written (an overwritten one is removed).
    """
    config = config or SimulationConfig()
    validate(config)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise Slam6dError(f"{out}: exists and is not a directory")
    stale = sorted(p for p in out.iterdir() if _SCAN_FILE.match(p.name)) if out.is_dir() else []
    if stale and not overwrite:
        raise Slam6dError(
            f"{out}: already holds {len(stale)} scan file(s); choose an empty directory or overwrite them (--overwrite)"
        )
    for old in stale:
        old.unlink()
    out.mkdir(parents=True, exist_ok=True)
    simulation = simulated_scans(config)
    paths, counts = [], []
    for index, (points, odo_pose) in enumerate(zip(simulation.scans(), simulation.odometry, strict=True)):
        native = UOS.points_to_native(points)
        odometry_pose = UOS.pose_to_native(odo_pose) if config.odometry else None
        paths.append(write_uos_scan(out, index, native, odometry_pose, decimals=config.decimals))
        counts.append(len(points))
        if progress is not None:
            progress(index + 1, config.scans)
    gt_file, odo_file, params_file = out / "ground_truth_kitti.txt", out / "odometry_kitti.txt", out / "simulation.json"
    write_kitti_poses(gt_file, [UOS.pose_to_native(p) for p in simulation.truth])
    if config.odometry:
        write_kitti_poses(odo_file, [UOS.pose_to_native(p) for p in simulation.odometry])
    else:
        odo_file.unlink(missing_ok=True)
    parameters = {
        "generator": "slam6d simulate",
        "config": dataclasses.asdict(simulation.config),
        "format": "uos (cm, left-handed, y up); .pose files and odometry_kitti.txt hold odometry"
        if config.odometry
        else "uos (cm, left-handed, y up); no odometry: no .pose files",
        "ground_truth": gt_file.name,
        "odometry": odo_file.name if config.odometry else None,
        # the odometry's roll and pitch are an inclinometer's (slam6d.motion.drifting_odometry): absolute,
        # not accumulated, so `slam6d run` may hold each scan's tilt to them (slam6d.attitude)
        "inclinometer": {"roll_pitch_noise_deg": config.odometry_tilt_noise_deg}
        if config.odometry and config.odometry_tilt_noise_deg > 0
        else None,
        "path_length_m": round(simulation.scene.route.length, 3),
        "scene_objects": simulation.scene.objects,
        "scene_triangles": len(simulation.scene.triangles),
        "points_per_scan": counts,
    }
    params_file.write_text(json.dumps(parameters, indent=1) + "\n")
    return SimulatedSession(
        out,
        paths,
        simulation.truth,
        simulation.odometry,
        counts,
        gt_file,
        odo_file if config.odometry else None,
        params_file,
        simulation.scene.route.length,
    )
