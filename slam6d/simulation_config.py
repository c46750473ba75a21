"""What shapes a simulated session, as plain data: the sensor, world and motion by name, and their settings.

Its own module so that the worlds and motions (which build from these values) and the simulator
(which chooses the defaults where a field is None, :func:`slam6d.simulate.resolved`) all depend on
it, and not on each other.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SimulationConfig:
    """Everything that shapes a simulated session; lengths in metres, angles in degrees.

    Fields left at None take the value that suits the rest: the world's sensor and motion, the
    sensor's shot count, range and noise, the motion's sensor height (see :func:`slam6d.simulate.resolved`).
    """

    seed: int = 0
    scans: int = 20
    points_per_scan: int | None = None  # laser shots per scan; misses and too-near hits return nothing
    sensor: str | None = None  # see slam6d.sensors.SENSORS; None: the world's (loop: rotating-sick)
    world: str = "loop"  # see slam6d.worlds.WORLDS
    motion: str | None = None  # see slam6d.motion.MOTIONS; None: the world's (loop: robot)
    odometry: bool = True  # write the drifting odometry as .pose files and odometry_kitti.txt
    elevation_min_deg: float = -40.0  # fan (rotating-sick) or tilt (tilting-sick) limits
    elevation_max_deg: float = 50.0
    loop_length: float = 32.0  # the loop world is a rounded rectangle around a block
    loop_width: float = 20.0
    closing_gap: float = 0.6  # how far along the route the robot's last stop is short of its first
    sensor_height: float | None = None  # above the ground; None: the motion's (robot 0.5 m)
    min_range: float = 0.6  # the platform's own body
    max_range: float | None = None  # None: the sensor's (SICK 30 m)
    range_noise: float | None = None  # std dev; None: the sensor's (SICK 1 cm)
    terrain_amplitude: float = 0.5  # loop world: of the smooth height field; slopes reach ~5-8°
    buildings: int = 7  # loop world: around the loop, besides the block inside it
    walls: int = 5
    cars: int = 4
    poles: int = 5
    trees: int = 22
    odometry_scale_error: float = 0.02  # relative error of every travelled distance
    odometry_yaw_drift_deg_per_m: float = 0.1
    odometry_turn_error: float = 0.04  # fraction of each turn misjudged (skid steering)
    odometry_translation_noise: float = 0.01  # std dev as a fraction of the step length
    odometry_yaw_noise_deg: float = 0.3
    odometry_height_noise: float = 0.02  # random walk per step
    odometry_tilt_noise_deg: float = 0.3  # inclinometer noise on roll and pitch, not accumulating
    decimals: int = 2  # of the centimetre coordinates written to the .3d files
