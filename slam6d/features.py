"""Feature-based global registration: FPFH descriptors matched with RANSAC (open3d), no start needed.

The octree search (:mod:`slam6d.initial_guess`) looks near a start; when the start is far off (no
odometry and a sharp turn, a robot that was carried, a first scan of a new session) nothing near it
fits. Fast Point Feature Histograms (Rusu et al. 2009) describe the local shape around each point of a
downsampled cloud independently of the pose, so putative correspondences come from matching
descriptors, and RANSAC over triples of them (with edge-length and distance checks) finds the
rigid motion most of them agree on, wherever the scans sit. It is the fallback, not the default:
it is coarser than the octree search (one voxel, half a metre on room-sized scans) and random, but
it does not care how far the start was.

open3d is imported on first use: loading it takes a few seconds that a run which never needs the
fallback should not pay; and without its plotly viewer (:mod:`slam6d.open3d_viewer`), half of its
import cost.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam6d.initial_guess import cloud_extent
from slam6d.octree import as_points, reduce_points
from slam6d.open3d_viewer import defer_plotly_viewer

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FeatureConfig:
    """Settings of the FPFH + RANSAC search. Lengths are multiples of the voxel size.

    ``voxel_size`` None picks ``extent_fraction`` of the model's extent (0.5 m for a 25 m scene,
    a few millimetres for the Stanford bunny), so the descriptors see the same amount of structure
    whatever the scale. Normals use ``normal_radius`` voxels, descriptors ``feature_radius`` voxels
    (FPFH needs a neighbourhood several times the sample spacing to be distinctive). RANSAC accepts
    pairs within ``inlier_distance`` voxels, tries at most ``max_iterations`` hypotheses and stops
    early at ``confidence``. open3d runs RANSAC's hypotheses on several threads, so even a seeded
    run is not repeatable and now and then settles early on a wrong alignment (a simulated VLP-16
    pair: 1 in 40 runs ended at fitness 0.83 and 0.72 m off after ICP, against 0.94-0.99 and 3 cm);
    it is run ``runs`` times (seeds ``seed``, ``seed + 1``, ...) on the same descriptors and the
    run with the highest fitness is kept.
    """

    voxel_size: float | None = None
    extent_fraction: float = 0.02
    normal_radius: float = 2.0
    feature_radius: float = 5.0
    inlier_distance: float = 1.5
    edge_length_ratio: float = 0.9
    max_iterations: int = 100_000
    confidence: float = 0.999
    mutual_filter: bool = False
    seed: int = 0
    runs: int = 3

    def __post_init__(self) -> None:
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ValueError(f"voxel_size must be positive (or None for automatic), got {self.voxel_size}")
        if not 0 < self.extent_fraction < 1:
            raise ValueError(f"extent_fraction must be in (0, 1), got {self.extent_fraction}")
        if not (self.normal_radius > 0 and self.feature_radius > 0 and self.inlier_distance > 0):
            raise ValueError("normal_radius, feature_radius and inlier_distance must be positive")
        if not 0 < self.edge_length_ratio < 1:
            raise ValueError(f"edge_length_ratio must be in (0, 1), got {self.edge_length_ratio}")
        if self.max_iterations < 1 or not 0 < self.confidence < 1:
            raise ValueError("max_iterations must be >= 1 and confidence in (0, 1)")
        if self.runs < 1:
            raise ValueError(f"runs must be at least 1, got {self.runs}")

    def voxel_for(self, model_points: FloatArray) -> float:
        return self.voxel_size if self.voxel_size is not None else self.extent_fraction * cloud_extent(model_points)


@dataclass
class FeatureGuess:
    """Outcome of :func:`feature_guess`: the data->model transform RANSAC chose and how well it held.

    ``fitness`` is the fraction of the downsampled data points with a model point within the inlier
    distance under ``transform``, ``inlier_rmse`` their RMS distance (metres), ``correspondences`` the
    RANSAC inliers among the descriptor matches.
    """

    transform: FloatArray
    fitness: float
    inlier_rmse: float
    correspondences: int
    model_points: int
    data_points: int
    voxel_size: float
    config: FeatureConfig
    seconds: float = field(default=0.0)


def _cloud(points: FloatArray, voxel: float, config: FeatureConfig) -> tuple[Any, Any]:
    """The cloud reduced to one real point per voxel, with normals and FPFH descriptors (open3d objects)."""
    import open3d as o3d  # loaded by feature_guess

    reduced = points[reduce_points(points, voxel)]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(reduced))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=config.normal_radius * voxel, max_nn=30))
    features = o3d.pipelines.registration.compute_fpfh_feature(  # type: ignore[call-arg]  # the stubs miss the overload without indices
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=config.feature_radius * voxel, max_nn=100)
    )
    return cloud, features


def feature_guess(
    model_points: FloatArray, data_points: FloatArray, config: FeatureConfig | None = None
) -> FeatureGuess:
    """Global data->model transform from FPFH correspondences and RANSAC; independent of any start."""
    defer_plotly_viewer()
    import open3d as o3d

    began = time.perf_counter()
    config = config or FeatureConfig()
    model_points = as_points(model_points, "model points")
    data_points = as_points(data_points, "data points")
    voxel = config.voxel_for(model_points)
    model, model_features = _cloud(model_points, voxel, config)
    data, data_features = _cloud(data_points, voxel, config)
    registration = o3d.pipelines.registration
    distance = config.inlier_distance * voxel
    results = []
    for run in range(config.runs):
        o3d.utility.random.seed(config.seed + run)
        results.append(
            registration.registration_ransac_based_on_feature_matching(
                data,
                model,
                data_features,
                model_features,
                config.mutual_filter,
                distance,
                registration.TransformationEstimationPointToPoint(False),
                3,
                [
                    registration.CorrespondenceCheckerBasedOnEdgeLength(config.edge_length_ratio),
                    registration.CorrespondenceCheckerBasedOnDistance(distance),
                ],
                registration.RANSACConvergenceCriteria(config.max_iterations, config.confidence),
            )
        )
    result = max(results, key=lambda r: (r.fitness, -r.inlier_rmse))
    return FeatureGuess(
        transform=np.array(result.transformation, dtype=np.float64),
        fitness=float(result.fitness),
        inlier_rmse=float(result.inlier_rmse),
        correspondences=len(result.correspondence_set),
        model_points=len(model.points),
        data_points=len(data.points),
        voxel_size=voxel,
        config=config,
        seconds=time.perf_counter() - began,
    )
