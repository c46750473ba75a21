"""Registered points made ready for the fly-through renderer, and the colours they are drawn in.

A :class:`PointScene` stores points as float32 offsets from a scene origin (float32 world
coordinates lose millimetres a few kilometres out) sorted along a Morton curve, which keeps
neighbouring points' z-buffer writes in cache. Colour ramps use percentiles, not min/max, so a
few stray returns do not wash them out.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix, transform_points
from slam6d.scan import ScanSequence
from slam6d.scan_store import ScanStore

if TYPE_CHECKING:
    from slam6d.camera_path import CameraPath
    from slam6d.scan_levels import ScanLevels

STREAM_BUDGET = 256 * 10**6  # bytes of full clouds held at once while a stored map is thinned for rendering

ColorMode = Literal["height", "scan", "intensity", "white"]
COLOR_MODES: tuple[str, ...] = ("height", "scan", "intensity", "white")
ProgressFn = Callable[[int, int], None]


@dataclass
class PointScene:
    """Points prepared for rendering: float32 offsets from ``origin``, Morton-ordered, with per-point attributes."""

    origin: NDArray[np.float64]
    points: NDArray[np.float32]
    scan_index: NDArray[np.int32]
    intensity: NDArray[np.float32] | None
    scan_poses: list[Matrix] = field(default_factory=list)
    scan_names: list[str] = field(default_factory=list)
    total_points: int = 0  # before downsampling
    read_bytes: int = 0  # of scan points read from disk to build a streamed scene (0: built in memory)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def scan_positions(self) -> NDArray[np.float64]:
        return np.array([p[:3, 3] for p in self.scan_poses], dtype=np.float64).reshape(-1, 3)

    def world_points(self) -> NDArray[np.float64]:
        return self.points.astype(np.float64) + self.origin

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        if len(self) == 0:
            return self.origin.copy(), self.origin.copy()
        return self.points.min(axis=0).astype(np.float64) + self.origin, self.points.max(axis=0).astype(
            np.float64
        ) + self.origin


def _morton_order(points: NDArray[np.float64], cell: float) -> NDArray[np.intp]:
    """Order points along a Z-order curve of ``cell``-sized voxels, so nearby points are nearby in memory."""
    q = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    q = np.clip(q, 0, (1 << 21) - 1).astype(np.uint64)
    code = np.zeros(len(points), dtype=np.uint64)
    for axis in range(3):
        v = q[:, axis]
        v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
        v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
        v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
        v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
        v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
        code |= v << np.uint64(axis)
    return np.argsort(code, kind="stable")


def scene_from_points(
    points: NDArray[np.floating],
    scan_index: NDArray[np.integer] | None = None,
    intensity: NDArray[np.floating] | None = None,
    scan_poses: list[Matrix] | None = None,
    scan_names: list[str] | None = None,
    total_points: int | None = None,
) -> PointScene:
    """Wrap world points (canonical frame) for rendering."""
    world = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = world.shape[0]
    index = np.zeros(n, dtype=np.int32) if scan_index is None else np.asarray(scan_index, dtype=np.int32)
    if index.shape != (n,) or (intensity is not None and np.shape(intensity) != (n,)):
        raise ValueError("scan_index and intensity must have one entry per point")
    if n == 0:
        return PointScene(np.zeros(3), np.zeros((0, 3), np.float32), index, None, scan_poses or [], scan_names or [], 0)
    lo, hi = world.min(axis=0), world.max(axis=0)
    origin = 0.5 * (lo + hi)
    extent = float(np.max(hi - lo))
    order = _morton_order(world, max(extent / (1 << 10), 1e-3))
    return PointScene(
        origin=origin,
        points=np.ascontiguousarray((world[order] - origin).astype(np.float32)),
        scan_index=np.ascontiguousarray(index[order]),
        intensity=None if intensity is None else np.asarray(intensity, dtype=np.float32)[order],
        scan_poses=list(scan_poses or []),
        scan_names=list(scan_names or []),
        total_points=n if total_points is None else total_points,
    )


def scene_from_sequence(sequence: ScanSequence, max_points: int | None = 2_000_000, seed: int = 0) -> PointScene:
    """Registered points of every scan (at its current pose), uniformly thinned to at most ``max_points``.

    Thinning is a random sample with the same fraction for every scan, so no scan vanishes and the
    result does not depend on the scan order. Scans without intensity get NaN there (shown grey).
    """
    rng = np.random.default_rng(seed)
    return _thinned_scene(
        [len(scan) for scan in sequence],
        lambda k, fraction: _random_share(sequence[k].world_points(), sequence[k].intensity, fraction, rng),
        [scan.pose.copy() for scan in sequence],
        [scan.name for scan in sequence],
        max_points,
        any(scan.intensity is not None for scan in sequence),
    )


def scene_from_store(
    store: ScanStore, poses: Sequence[Matrix] | None = None, max_points: int | None = 2_000_000, seed: int = 0
) -> PointScene:
    """:func:`scene_from_sequence` streamed from a scan store: one scan read at a time (through the
    store's memory budget) and only its thinned share kept, so a map of any size renders within
    the budget plus ``max_points``. ``poses`` (canonical frame) default to the store's own."""
    placed = _poses_for(store, poses)
    rng = np.random.default_rng(seed)
    before = store.read_bytes
    scene = _thinned_scene(
        [int(c) for c in store.counts],
        lambda k, fraction: _random_share(transform_points(placed[k], store.points(k)), None, fraction, rng),
        placed,
        list(store.names),
        max_points,
        False,
    )
    scene.read_bytes = store.read_bytes - before
    return scene


def scene_from_levels(
    levels: ScanLevels, poses: Sequence[Matrix] | None = None, max_points: int | None = 2_000_000
) -> PointScene:
    """The map read from a level-of-detail store (:mod:`slam6d.scan_levels`): each scan's share of
    ``max_points`` is a *prefix* of its progressively ordered points, an even spatial sample read
    with one file read. Only the points kept are ever read, so a 1,000-scan session costs
    ``max_points`` of reading and memory however large it is; ``poses`` as in :func:`scene_from_store`."""
    store = levels.store
    placed = _poses_for(store, poses)

    def prefix(k: int, fraction: float) -> tuple[NDArray[np.float64], None]:
        keep = int(store.counts[k]) if fraction >= 1.0 else round(float(store.counts[k]) * fraction)
        return transform_points(placed[k], store.prefix(k, keep).astype(np.float64)), None

    before = store.read_bytes
    scene = _thinned_scene([int(c) for c in store.counts], prefix, placed, list(store.names), max_points, False)
    scene.read_bytes = store.read_bytes - before
    return scene


def _poses_for(store: ScanStore, poses: Sequence[Matrix] | None) -> list[Matrix]:
    placed = list(store.poses) if poses is None else [np.asarray(p, dtype=np.float64) for p in poses]
    if len(placed) != len(store):
        raise Slam6dError(f"{store.directory}: {len(placed)} poses for {len(store)} stored scans")
    return placed


def _random_share(
    world: NDArray[np.float64], intensity: NDArray[np.float32] | None, fraction: float, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float32] | None]:
    """A random ``fraction`` of one scan's points (all of them at 1), the same draw for points and intensity."""
    if fraction >= 1.0:
        return world, intensity
    keep = rng.random(len(world)) < fraction
    return world[keep], None if intensity is None else intensity[keep]


def _thinned_scene(
    sizes: Sequence[int],
    load: Callable[[int, float], tuple[NDArray[np.float64], NDArray[np.float32] | None]],
    poses: list[Matrix],
    names: list[str],
    max_points: int | None,
    any_intensity: bool,
) -> PointScene:
    """Each scan's world points thinned by one fraction (``load(k, fraction)``, asked once per scan, in order)."""
    total = int(sum(sizes))
    fraction = 1.0 if not max_points or total <= max_points else max_points / total
    chunks, indices, intensities = [], [], []
    for i in range(len(sizes)):
        pts, intensity = load(i, fraction)
        chunks.append(pts)
        indices.append(np.full(len(pts), i, dtype=np.int32))
        if any_intensity:
            values = intensity if intensity is not None else np.full(len(pts), np.nan, np.float32)
            intensities.append(np.asarray(values, dtype=np.float32))
    points = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    return scene_from_points(
        points,
        np.concatenate(indices) if indices else None,
        np.concatenate(intensities) if any_intensity else None,
        poses,
        names,
        total,
    )


def load_render_input(
    source: Path | str,
    format_name: str | None = None,
    poses_file: Path | None = None,
    max_points: int | None = 2_000_000,
    progress: ProgressFn | None = None,
    with_intensity: bool = False,
) -> tuple[PointScene, CameraPath | None]:
    """Points with their latest poses from a session folder or a scan directory/file, plus any saved path.

    A folder holding ``session.toml`` is opened as a workbench session (its latest registration and
    its saved camera path, if any), its points streamed from the level store in its cache
    (:func:`scene_from_levels`; the store keeps no intensity, so ``with_intensity`` reads the parsed
    scans instead); a scan store (``slam6d run --memory-budget``'s ``OUT/scan_store``,
    with ``poses_file`` its ``poses_kitti.txt``) is streamed (:func:`scene_from_store`); anything else is read with :func:`slam6d.io.read_sequence`.
    """
    source = Path(source)
    camera_path: CameraPath | None = None
    if ScanStore.holds(source):  # streamed: never the whole session in memory
        store = ScanStore(source, STREAM_BUDGET)
        poses = None
        if poses_file is not None:
            from slam6d.io.poses import read_poses_file

            poses = [store.convention.pose_to_canonical(p) for p in read_poses_file(poses_file)]
        return scene_from_store(store, poses, max_points), None
    if source.is_dir() and (source / "session.toml").is_file():
        try:
            from slam6d.session import Session
        except ModuleNotFoundError as exc:  # pragma: no cover - only while sessions are not installed
            raise Slam6dError(f"{source}: is a session folder, but this installation cannot open sessions") from exc
        session = Session.open(source)
        camera_path = _session_camera_path(session)
        if not with_intensity:  # streamed from the session's level store: never the whole session in memory
            from slam6d.scan_levels import session_levels

            # built (once, from the parsed scans) only when the cache has none for the scans as they are
            levels = session_levels(session, lambda: session.load_sequence(progress).scans)
            return scene_from_levels(levels, session.poses(), max_points), camera_path
        sequence = session.load_sequence(progress)
    else:
        from slam6d.io import read_sequence

        sequence = read_sequence(source, format_name, poses_file=poses_file, progress=progress)
    return scene_from_sequence(sequence, max_points), camera_path


def _session_camera_path(session: object) -> CameraPath | None:
    """The path a user saved in the session, whichever form the session hands it over in."""
    from slam6d.camera_path import CameraPath, camera_path_from_dict, load_camera_path

    getter = getattr(session, "camera_path", None)
    saved = getter() if callable(getter) else getter
    if saved is None or isinstance(saved, CameraPath):
        return saved
    if isinstance(saved, list):  # Session.camera_path(): the keyframe list the workbench saved; [] is none yet
        return (
            camera_path_from_dict({"keyframes": saved}, source=getattr(session, "folder", "session")) if saved else None
        )
    if isinstance(saved, dict):
        return camera_path_from_dict(saved, source="session")
    if isinstance(saved, str | Path):
        return load_camera_path(Path(saved))
    raise Slam6dError(f"session camera path has an unexpected type {type(saved).__name__}")


def _ramp(stops: Sequence[tuple[float, float, float]], n: int = 256) -> NDArray[np.uint8]:
    s = np.asarray(stops, dtype=np.float64)
    x = np.linspace(0.0, 1.0, n)
    xp = np.linspace(0.0, 1.0, len(s))
    return np.stack([np.interp(x, xp, s[:, c]) for c in range(3)], axis=1).round().astype(np.uint8)


# Blue-green-yellow after viridis, with its dark violet end lifted so low points stay clear of a dark background.
_HEIGHT_LUT = _ramp([(72, 60, 170), (49, 104, 180), (33, 145, 140), (94, 201, 98), (253, 231, 37)])


_INTENSITY_LUT = _ramp([(70, 70, 80), (150, 150, 155), (245, 240, 225)])


_NO_DATA_GREY = np.array([140, 140, 140], dtype=np.uint8)


def _through_lut(values: NDArray[np.floating], lut: NDArray[np.uint8], low_pct: float, high_pct: float) -> NDArray:
    finite = np.isfinite(values)
    out = np.empty((len(values), 3), dtype=np.uint8)
    out[:] = _NO_DATA_GREY
    if finite.any():
        lo, hi = np.percentile(values[finite], [low_pct, high_pct])
        scaled = (values[finite] - lo) / max(hi - lo, 1e-9)
        out[finite] = lut[np.clip(scaled * (len(lut) - 1), 0, len(lut) - 1).astype(np.intp)]
    return out


def scan_palette(count: int) -> NDArray[np.uint8]:
    """Distinct, stable colours per scan: hues spaced by the golden angle, so neighbours differ."""
    hue = (np.arange(count) * 0.618033988749895) % 1.0
    sat, val = 0.65, 0.95
    k = (np.array([5.0, 3.0, 1.0])[None, :] + hue[:, None] * 6.0) % 6.0
    rgb = val - val * sat * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return (rgb * 255).round().astype(np.uint8)


def point_colors(scene: PointScene, mode: str) -> NDArray[np.uint8]:
    """Per-point RGB for a colour mode; percentiles (not min/max) so outliers do not wash the ramp out."""
    if mode == "height":
        return _through_lut(scene.points[:, 2].astype(np.float64), _HEIGHT_LUT, 2.0, 98.0)
    if mode == "scan":
        count = max(len(scene.scan_poses), int(scene.scan_index.max()) + 1 if len(scene) else 1)
        return scan_palette(count)[scene.scan_index]
    if mode == "intensity":
        if scene.intensity is None:
            raise Slam6dError("colour mode 'intensity': this data carries no intensity; use height, scan or white")
        return _through_lut(scene.intensity.astype(np.float64), _INTENSITY_LUT, 1.0, 99.0)
    if mode == "white":
        return np.full((len(scene), 3), 225, dtype=np.uint8)
    raise ValueError(f"unknown colour mode '{mode}'; choose one of {', '.join(COLOR_MODES)}")
