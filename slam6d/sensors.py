"""Laser scanners the simulator can fly: their beam patterns, ranges and noise.

Users bring whatever their robot carries, so the engine has to be tested on the beam patterns of
real devices, not only on the seed's rotating SICK fan. A multi-beam lidar samples the world in
rings (one per laser, at fixed elevations) that are sparse vertically and dense horizontally; a
2D fan swept by a motor samples it densely in both. The elevation tables below are the
manufacturers' published ones (VLP-16, HDL-32E, Ouster OS1-64 exactly; HDL-64E S2's per-unit
calibration as its nominal two blocks), listed in firing order, so a simulated scan's points come
in the order the device delivers them: column after column clockwise from straight ahead, within a
column the lasers in firing order.

Directions are unit vectors in the scanner frame (x forward, y left, z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import one_of

POINTS_PER_LINE = 181  # a SICK LMS 2xx: 181 readings per 180° sweep


def _interleaved(lower: NDArray[np.floating], upper: NDArray[np.floating]) -> tuple[float, ...]:
    """Two banks fired in pairs (lower[0], upper[0], lower[1], …), as Velodyne's laser IDs run."""
    return tuple(float(v) for pair in zip(lower, upper, strict=True) for v in pair)


@dataclass(frozen=True)
class Sensor:
    """One scanner model. ``elevations_deg`` is None for the swept 2D fans, whose pattern depends
    on the shot count and elevation limits of the session (see :func:`beam_directions`)."""

    name: str
    description: str
    elevations_deg: tuple[float, ...] | None  # multi-beam lidars: one per laser, in firing order
    native_shots: int  # shots per scan (per revolution at 10 Hz for the spinning lidars)
    max_range: float  # metres
    range_noise: float  # standard deviation, metres

    @property
    def beams(self) -> int:
        """Lasers of a multi-beam lidar; the readings per line of a 2D fan."""
        return len(self.elevations_deg) if self.elevations_deg is not None else POINTS_PER_LINE

    @property
    def is_multi_beam(self) -> bool:
        return self.elevations_deg is not None

    def columns(self, shots: int) -> int:
        """Azimuth steps per revolution of a multi-beam lidar for a budget of ``shots``."""
        return max(1, round(shots / self.beams))


_VLP16 = _interleaved(np.linspace(-15.0, -1.0, 8), np.linspace(1.0, 15.0, 8))
_HDL32 = _interleaved(-30.67 + 4.0 / 3.0 * np.arange(16), -30.67 + 4.0 / 3.0 * np.arange(16, 32))
_HDL64 = _interleaved(np.linspace(2.0, -8.33, 32), np.linspace(-8.87, -24.9, 32))
_OS1_64 = tuple(float(v) for v in np.linspace(16.6, -16.6, 64))  # channel 0 at the top, as Ouster numbers them

SENSORS: dict[str, Sensor] = {
    sensor.name: sensor
    for sensor in (
        Sensor(
            "rotating-sick",
            "a vertical 181-reading SICK fan turned 360° about the vertical axis (the seed's 3D scanner)",
            None,
            20_000,
            30.0,
            0.01,
        ),
        Sensor(
            "tilting-sick",
            "Kurt3D's horizontal 180° SICK fan pitched from low to high: the front half only",
            None,
            20_000,
            30.0,
            0.01,
        ),
        Sensor("vlp16", "Velodyne VLP-16: 16 lasers -15°..+15° every 2°, 0.2° at 10 Hz", _VLP16, 16 * 1800, 100.0, 0.03),
        Sensor("hdl32", "Velodyne HDL-32E: 32 lasers -30.67°..+10.67°, 0.166° at 10 Hz", _HDL32, 32 * 2172, 100.0, 0.02),
        Sensor("hdl64", "Velodyne HDL-64E S2: 64 lasers -24.9°..+2°, 0.17° at 10 Hz", _HDL64, 64 * 2083, 120.0, 0.02),
        Sensor("os1-64", "Ouster OS1-64: 64 beams ±16.6° uniform, 1024 columns (1024x10 mode)", _OS1_64, 64 * 1024, 120.0, 0.03),
    )
}  # fmt: skip
SENSOR_NAMES = tuple(SENSORS)
LEGACY_PATTERNS = {"rotating": "rotating-sick", "tilting": "tilting-sick"}  # the former --pattern values


def get_sensor(name: str) -> Sensor:
    """The sensor called ``name`` (the former pattern names ``rotating``/``tilting`` are accepted)."""
    return one_of(SENSORS, LEGACY_PATTERNS.get(name, name), "sensor")


def beam_directions(
    sensor: Sensor, shots: int, elevation_min_deg: float = -40.0, elevation_max_deg: float = 50.0
) -> NDArray[np.float64]:
    """Unit ray directions of one scan in firing order.

    Multi-beam lidars: ``shots / beams`` columns (rounded) spaced evenly over 360°, clockwise from
    straight ahead as the devices spin; ``shots = sensor.native_shots`` gives the device's own
    horizontal resolution. The SICK fans: ``shots / 181`` lines between the elevation limits.
    """
    if sensor.elevations_deg is not None:
        columns = sensor.columns(shots)
        azimuth = -2 * np.pi * np.arange(columns) / columns
        elevation = np.radians(np.array(sensor.elevations_deg))
        a, e = np.meshgrid(azimuth, elevation, indexing="ij")  # column-major: lasers within a column
        return np.c_[(np.cos(e) * np.cos(a)).ravel(), (np.cos(e) * np.sin(a)).ravel(), np.sin(e).ravel()]
    lines = max(1, round(shots / POINTS_PER_LINE))
    low, high = np.radians(elevation_min_deg), np.radians(elevation_max_deg)
    if sensor.name == "rotating-sick":
        # A vertical fan (181 readings from low to high elevation) turned about z through 360°.
        elevation = np.linspace(low, high, POINTS_PER_LINE)
        yaw = 2 * np.pi * np.arange(lines) / lines
        e, a = np.meshgrid(elevation, yaw)
        return np.c_[(np.cos(e) * np.cos(a)).ravel(), (np.cos(e) * np.sin(a)).ravel(), np.sin(e).ravel()]
    # Kurt3D: a horizontal 180° fan whose plane is pitched from low to high, one line per step.
    azimuth = np.radians(np.linspace(-90.0, 90.0, POINTS_PER_LINE))
    tilt = np.linspace(low, high, lines)
    a, t = np.meshgrid(azimuth, tilt)
    return np.c_[(np.cos(a) * np.cos(t)).ravel(), np.sin(a).ravel(), (np.cos(a) * np.sin(t)).ravel()]
