"""An in-memory simulated session (the project's own simulator, no files) for fast pipeline tests."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam6d.geometry import Matrix
from slam6d.scan import Scan, ScanSequence
from slam6d.simulate import SimulationConfig, simulated_scans


@dataclass
class SimulatedLoop:
    sequence: ScanSequence  # scans carry the drifting odometry as their poses (has_pose False without odometry)
    truth: list[Matrix]
    odometry: list[Matrix]


def simulated_loop(
    scans: int = 12,
    points: int | None = 8000,
    seed: int = 3,
    first: int | None = None,
    **overrides: float | str | bool | None,
) -> SimulatedLoop:
    """``first`` keeps only the first scans of the session (the route still has ``scans`` stops).

    ``overrides`` are :class:`SimulationConfig` fields, e.g. ``sensor="vlp16", world="indoor",
    motion="handheld", odometry=False``; ``points=None`` takes the sensor's own shot count.
    Without odometry the scans sit at the identity with ``has_pose`` False, as a reader leaves
    scans that have no pose file.
    """
    config = SimulationConfig(seed=seed, scans=scans, points_per_scan=points, **overrides)  # type: ignore[arg-type]
    simulation = simulated_scans(config)
    truth, odometry = simulation.truth[:first], simulation.odometry[:first]
    clouds = [cloud for _, cloud in zip(truth, simulation.scans(), strict=False)]  # cast only the scans kept
    sequence = ScanSequence(
        [
            Scan(c, o.copy() if config.odometry else np.eye(4), name=f"scan{k:03d}", has_pose=config.odometry)
            for k, (c, o) in enumerate(zip(clouds, odometry, strict=True))
        ]
    )
    return SimulatedLoop(sequence, truth, odometry)
