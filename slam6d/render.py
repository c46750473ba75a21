"""Software point-cloud renderer for fly-through videos, on the CPU without a browser or GPU.

Registered points are projected through a pinhole camera into a z-buffer; each point becomes a
square splat whose side shrinks with distance (near points must cover the gaps between them, far
ones must not smear). Eye-dome lighting (EDL) darkens pixels that lie behind their neighbours in
log depth, so edges and surfaces read even when every point has the same colour; optional depth
fog fades distant points into the background.

Camera convention (OpenCV, the one viser uses too): in the camera frame x points right, y down and
z forward (the viewing direction). ``Camera.pose`` is ``world_from_camera`` in the canonical world
frame (right-handed, metres, z up). A camera-frame point (x, y, z) with z > 0 lands at
``u = fx x / z + cx``, ``v = fy y / z + cy``; pixel (col, row) covers ``[col, col+1) x [row, row+1)``,
so its centre is at (col + 0.5, row + 0.5) and ``cx = width / 2`` is the middle of the image.

The z-buffer is a numba kernel: every thread splats its share of the points into its own buffer of
packed (depth, point index) 64-bit keys, so there are no write races and no atomics; a parallel
pass then takes the per-pixel minimum. The points come prepared and coloured by
:mod:`slam6d.point_scene`; the frames go to :mod:`slam6d.video`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numba
import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from slam6d.errors import Cancelled, Slam6dError
from slam6d.geometry import Matrix, invert
from slam6d.point_scene import COLOR_MODES, PointScene, ProgressFn, point_colors
from slam6d.video import EncoderOptions, FrameSink

if TYPE_CHECKING:
    from slam6d.camera_path import CameraPath

Shading = Literal["edl", "depth", "edl+depth", "none"]
SHADINGS: tuple[str, ...] = ("edl", "depth", "edl+depth", "none")
CancelFn = Callable[[], bool]

# Depth is stored in the upper 32 bits of a z-buffer key in units of 10 µm: exact enough to order
# points 0.1 mm apart, and far enough (42 km) for any scan. The lower 32 bits hold the point index.
_DEPTH_UNITS_PER_METRE = 1.0e5
_EMPTY_KEY = np.uint64(0xFFFFFFFFFFFFFFFF)


class RenderCancelledError(Cancelled):
    """The caller's cancel check returned True; no partial output is left behind."""


# ---------------------------------------------------------------- camera


@dataclass
class Camera:
    """A pinhole camera: ``pose`` is world_from_camera (OpenCV axes: x right, y down, z forward)."""

    pose: Matrix
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, pose: Matrix, width: int, height: int, fov_deg: float = 60.0) -> Camera:
        """Square pixels, centred principal point, ``fov_deg`` the *vertical* field of view (as viser's)."""
        if not 1.0 <= fov_deg < 179.0:
            raise ValueError(f"field of view must be within [1, 179) degrees, got {fov_deg}")
        f = 0.5 * height / math.tan(math.radians(fov_deg) / 2.0)
        return cls(np.asarray(pose, dtype=np.float64), f, f, width / 2.0, height / 2.0, int(width), int(height))

    @property
    def fov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.fy))

    def project(self, points: NDArray[np.floating]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel coordinates (N, 2) and camera-frame depth (N,) of world points, for checks and overlays."""
        camera_from_world = invert(self.pose)
        pc = (
            np.asarray(points, dtype=np.float64).reshape(-1, 3) @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * pc[:, 0] / pc[:, 2] + self.cx, self.fy * pc[:, 1] / pc[:, 2] + self.cy], axis=1)
        return uv, pc[:, 2]


# ---------------------------------------------------------------- kernels


BLOCK = 256  # points per culling block: consecutive in Morton order, so each block is spatially compact
_FAR_LOG = np.float32(1.0e30)  # log depth of an empty pixel: finite, so fastmath arithmetic stays exact


@njit(parallel=True, fastmath=True, cache=True)
def _block_spheres(points, block):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Bounding sphere (centre, radius) of every run of ``block`` consecutive points."""
    n = points.shape[0]
    count = (n + block - 1) // block
    centres = np.empty((count, 3), dtype=np.float64)
    radii = np.empty(count, dtype=np.float64)
    for b in prange(count):
        start = b * block
        stop = min(n, start + block)
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for i in range(start, stop):
            for a in range(3):
                lo[a] = min(lo[a], points[i, a])
                hi[a] = max(hi[a], points[i, a])
        r2 = 0.0
        for a in range(3):
            centres[b, a] = 0.5 * (lo[a] + hi[a])
            r2 += (0.5 * (hi[a] - lo[a])) ** 2
        radii[b] = math.sqrt(r2)
    return centres, radii


@njit(parallel=True, fastmath=True, cache=True)
def _splat_kernel(  # type: ignore[no-untyped-def]
    points, centres, radii, block, rot, trans, fx, fy, cx, cy, near, size_scale, max_size, planes, buffers
):  # pragma: no cover
    """Splat points into per-chunk z-buffers of packed (depth, index) keys.

    Blocks are dealt out round-robin, so every chunk gets a share of what the camera sees (a
    contiguous split would hand one thread the half of the map behind the camera). A block whose
    bounding sphere lies outside the view frustum (``planes``: unit normals in the camera frame,
    widened by half the largest splat) is skipped without touching its points.
    """
    n = points.shape[0]
    chunks, height, width = buffers.shape
    blocks = centres.shape[0]
    r00, r01, r02, t0 = rot[0, 0], rot[0, 1], rot[0, 2], trans[0]
    r10, r11, r12, t1 = rot[1, 0], rot[1, 1], rot[1, 2], trans[1]
    r20, r21, r22, t2 = rot[2, 0], rot[2, 1], rot[2, 2], trans[2]
    max_depth = 4294967295.0 / 1.0e5
    for c in prange(chunks):
        buf = buffers[c]  # left empty by the previous frame's resolve pass
        for b in range(c, blocks, chunks):
            bx, by, bz = centres[b, 0], centres[b, 1], centres[b, 2]
            px = r00 * bx + r01 * by + r02 * bz + t0
            py = r10 * bx + r11 * by + r12 * bz + t1
            pz = r20 * bx + r21 * by + r22 * bz + t2
            radius = radii[b]
            if pz + radius <= near:
                continue
            outside = False
            for k in range(4):
                if planes[k, 0] * px + planes[k, 1] * py + planes[k, 2] * pz < -radius:
                    outside = True
                    break
            if outside:
                continue
            for i in range(b * block, min(n, (b + 1) * block)):
                x = points[i, 0]
                y = points[i, 1]
                z = points[i, 2]
                zc = r20 * x + r21 * y + r22 * z + t2
                if zc <= near:
                    continue
                inv = 1.0 / zc
                u = fx * (r00 * x + r01 * y + r02 * z + t0) * inv + cx
                v = fy * (r10 * x + r11 * y + r12 * z + t1) * inv + cy
                # via int64: x86 has no direct float -> uint64 conversion, the emulation costs a branch
                key = (np.uint64(np.int64(min(zc, max_depth) * 1.0e5)) << np.uint64(32)) | np.uint64(i)
                size = int(size_scale * inv + 0.5)
                if size <= 1:
                    if 0.0 <= u < width and 0.0 <= v < height:
                        col = int(u)
                        row = int(v)
                        old = buf[row, col]
                        buf[row, col] = key if key < old else old  # branch-free: the outcome is random
                    continue
                if size > max_size:
                    size = max_size
                half = 0.5 * (size - 1)
                uf = u - half
                vf = v - half
                if uf >= width or vf >= height or uf + size <= 0.0 or vf + size <= 0.0:
                    continue
                c0 = math.floor(uf)
                r0 = math.floor(vf)
                c1 = min(c0 + size, width)
                r1 = min(r0 + size, height)
                c0 = max(c0, 0)
                r0 = max(r0, 0)
                for r in range(r0, r1):
                    for cc in range(c0, c1):
                        old = buf[r, cc]
                        buf[r, cc] = key if key < old else old


@njit(parallel=True, fastmath=True, cache=True)
def _resolve_kernel(buffers, pad, depth, log_depth, index):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Per-pixel minimum over the chunk buffers -> depth (inf if empty), point index (-1), and log2 depth
    into the interior of ``log_depth``, whose ``pad``-wide border stays empty so EDL needs no bounds checks.
    Leaves the chunk buffers empty again, so the splat pass needs no separate clearing sweep."""
    chunks, height, width = buffers.shape
    empty = np.uint64(0xFFFFFFFFFFFFFFFF)
    low_mask = np.uint64(0xFFFFFFFF)
    for r in prange(height):
        for c in range(width):
            best = buffers[0, r, c]
            buffers[0, r, c] = empty  # cleared here, while in cache, for the next frame
            for k in range(1, chunks):
                key = buffers[k, r, c]
                buffers[k, r, c] = empty
                if key < best:
                    best = key
            if best == empty:
                depth[r, c] = np.inf
                log_depth[r + pad, c + pad] = 1.0e30
                index[r, c] = -1
            else:
                d = max(np.float32((best >> np.uint64(32)) * 1.0e-5), np.float32(1e-5))
                depth[r, c] = d
                log_depth[r + pad, c + pad] = math.log2(d)
                index[r, c] = np.int32(best & low_mask)


# exp(-x) for x in [0, 24] in steps of 1/1024 (0 beyond): libm's exp per pixel cost more than all the rest
# of shading, and rounding to the nearest step is off by at most 0.12 of a colour level.
_EXP_STEPS = 1024.0
_EXP_LUT = np.exp(-np.arange(int(24 * _EXP_STEPS) + 1) / _EXP_STEPS).astype(np.float32)
_EXP_LUT[-1] = 0.0


@njit(parallel=True, fastmath=True, cache=True)
def _shade_kernel(  # type: ignore[no-untyped-def]
    depth, log_depth, pad, index, colors, background, edl_strength, edl_offsets, fog_distance, exp_lut, steps, image
):  # pragma: no cover
    """Colour every pixel: point colour x EDL factor, faded towards the background by depth fog.

    EDL response of a pixel = mean over its ring of neighbours of how much farther (in log depth)
    it is than each; only pixels behind a neighbour darken, which outlines edges and creases.
    Computed a row at a time over the padded log-depth image so the inner loops vectorise.
    Both exponentials (EDL factor, fog) come from ``exp_lut`` (exp(-k / steps) at k).
    """
    height, width = depth.shape
    neighbours = edl_offsets.shape[0]
    b0, b1, b2 = np.float32(background[0]), np.float32(background[1]), np.float32(background[2])
    last = exp_lut.shape[0] - 1
    beyond = np.float32(last)  # arguments are clamped as floats: huge ones must not overflow int conversion
    edl_q = np.float32(edl_strength / neighbours * steps)
    fog_q = np.float32(steps / fog_distance) if fog_distance > 0.0 else np.float32(0.0)
    half, top = np.float32(0.5), np.float32(255.0)
    for r in prange(height):
        response = np.zeros(width, dtype=np.float32)
        if edl_strength > 0.0:
            centre = log_depth[r + pad, pad : pad + width]
            for k in range(neighbours):
                rr = r + pad + edl_offsets[k, 0]
                c0 = pad + edl_offsets[k, 1]
                other = log_depth[rr, c0 : c0 + width]
                for c in range(width):
                    response[c] += max(centre[c] - other[c], np.float32(0.0))
        for c in range(width):
            i = index[r, c]
            if i < 0:
                image[r, c, 0] = np.uint8(b0)
                image[r, c, 1] = np.uint8(b1)
                image[r, c, 2] = np.uint8(b2)
                continue
            shade = exp_lut[int(min(response[c] * edl_q + half, beyond))]
            fog = exp_lut[int(min(depth[r, c] * fog_q + half, beyond))]
            k0 = shade * fog
            k1 = np.float32(1.0) - fog
            image[r, c, 0] = np.uint8(min(top, colors[i, 0] * k0 + b0 * k1 + half))
            image[r, c, 1] = np.uint8(min(top, colors[i, 1] * k0 + b1 * k1 + half))
            image[r, c, 2] = np.uint8(min(top, colors[i, 2] * k0 + b2 * k1 + half))


def _frustum_planes(camera: Camera, margin: float) -> NDArray[np.float64]:
    """Inward unit normals (camera frame) of the four side planes, the image widened by ``margin`` pixels."""
    left, right = camera.cx + margin, camera.width - camera.cx + margin
    top, bottom = camera.cy + margin, camera.height - camera.cy + margin
    planes = np.array(
        [[camera.fx, 0.0, left], [-camera.fx, 0.0, right], [0.0, camera.fy, top], [0.0, -camera.fy, bottom]]
    )
    return planes / np.linalg.norm(planes, axis=1, keepdims=True)


# ---------------------------------------------------------------- renderer


@dataclass
class RenderOptions:
    """How points look. ``point_size`` is a splat's world size in metres (its pixel size follows distance)."""

    color_mode: str = "height"
    shading: str = "edl+depth"
    point_size: float = 0.03
    max_splat: int = 8  # pixels; caps the cost and the blockiness of points right in front of the camera
    edl_strength: float = 20.0
    edl_radius: int = 1
    fog_distance: float | None = None  # metres; None: a third of the scene's (robust) extent
    background: tuple[int, int, int] = (18, 20, 26)
    near: float = 0.05

    def __post_init__(self) -> None:
        if self.color_mode not in COLOR_MODES:
            raise ValueError(f"unknown colour mode '{self.color_mode}'; choose one of {', '.join(COLOR_MODES)}")
        if self.shading not in SHADINGS:
            raise ValueError(f"unknown shading '{self.shading}'; choose one of {', '.join(SHADINGS)}")
        if self.point_size < 0 or self.max_splat < 1 or self.edl_radius < 1 or self.near <= 0:
            raise ValueError("point_size must be >= 0, max_splat and edl_radius >= 1, near > 0")


def _default_fog(scene: PointScene) -> float:
    """A third of the scene's extent, measured between percentiles so stray far returns do not count."""
    if len(scene) == 0:
        return 1.0
    sample = scene.points[:: max(1, len(scene) // 100_000)]
    lo, hi = np.percentile(sample, [2.0, 98.0], axis=0)
    return max(float(np.max(hi - lo)) / 3.0, 1.0)


class Renderer:
    """Renders one scene repeatedly; keeps its buffers between frames so a video allocates once."""

    def __init__(self, scene: PointScene, width: int, height: int, options: RenderOptions | None = None) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        self.scene = scene
        self.width, self.height = int(width), int(height)
        self.options = options or RenderOptions()
        self.colors = np.ascontiguousarray(point_colors(scene, self.options.color_mode))
        fog = self.options.fog_distance if self.options.fog_distance is not None else _default_fog(scene)
        self._fog = fog if self.options.shading in ("depth", "edl+depth") else 0.0
        self._edl = self.options.edl_strength if self.options.shading in ("edl", "edl+depth") else 0.0
        chunks = max(1, numba.get_num_threads())
        self._buffers = np.full((chunks, self.height, self.width), _EMPTY_KEY, dtype=np.uint64)
        self.depth = np.empty((self.height, self.width), dtype=np.float32)
        self.index = np.empty((self.height, self.width), dtype=np.int32)
        self._pad = int(self.options.edl_radius)
        self._log_depth = np.full((self.height + 2 * self._pad, self.width + 2 * self._pad), _FAR_LOG, dtype=np.float32)
        if len(scene):
            self._centres, self._radii = _block_spheres(scene.points, BLOCK)
        self._background = np.array(self.options.background, dtype=np.float64)
        # The eight neighbours EDL compares each pixel with, ``edl_radius`` pixels away.
        ring = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1)]
        self._edl_offsets = np.array(ring, dtype=np.int64) * int(self.options.edl_radius)

    def camera(self, pose: Matrix, fov_deg: float = 60.0) -> Camera:
        return Camera.from_fov(pose, self.width, self.height, fov_deg)

    def rasterize(self, camera: Camera) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """Z-buffer only: per-pixel depth along the camera's z (inf where empty) and point index (-1)."""
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(f"camera is {camera.width}x{camera.height}, renderer is {self.width}x{self.height}")
        camera_from_world = invert(camera.pose)
        rot = camera_from_world[:3, :3]
        trans = rot @ self.scene.origin + camera_from_world[:3, 3]  # points are stored relative to the origin
        if len(self.scene) == 0:
            self.depth.fill(np.inf)
            self._log_depth.fill(_FAR_LOG)
            self.index.fill(-1)
            return self.depth, self.index
        _splat_kernel(
            self.scene.points,
            self._centres,
            self._radii,
            BLOCK,
            np.ascontiguousarray(rot),
            np.ascontiguousarray(trans),
            float(camera.fx),
            float(camera.fy),
            float(camera.cx),
            float(camera.cy),
            float(self.options.near),
            float(self.options.point_size * camera.fx),
            int(self.options.max_splat),
            _frustum_planes(camera, 0.5 * self.options.max_splat + 1.0),
            self._buffers,
        )
        _resolve_kernel(self._buffers, self._pad, self.depth, self._log_depth, self.index)
        return self.depth, self.index

    def render(self, camera: Camera, out: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
        """An (height, width, 3) RGB image of the scene seen from ``camera``."""
        self.rasterize(camera)
        image = out if out is not None else np.empty((self.height, self.width, 3), dtype=np.uint8)
        colors = self.colors if len(self.colors) else np.zeros((1, 3), dtype=np.uint8)
        _shade_kernel(
            self.depth,
            self._log_depth,
            self._pad,
            self.index,
            colors,
            self._background,
            float(self._edl),
            self._edl_offsets,
            float(self._fog),
            _EXP_LUT,
            _EXP_STEPS,
            image,
        )
        return image


def prepare_kernels() -> None:
    """Load the renderer's compiled kernels by drawing one tiny frame.

    A fresh process spends about a second (several under load) in numba's first dispatch: its
    typing registries and the kernels' on-disk cache. That does not depend on the map, so
    ``slam6d render`` runs this on a thread while the map is read instead of after it.
    """
    from slam6d.point_scene import scene_from_points

    tiny = Renderer(scene_from_points(np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 2.5]])), 8, 8)
    tiny.render(tiny.camera(np.eye(4)))


@dataclass
class RenderResult:
    """What a render wrote, and where its time went: ``seconds`` from the first frame to the file in
    place, of which ``render_seconds`` drawing frames and ``encoder_wait_seconds`` waiting for the
    encoder to free a buffer (zero when encoding keeps up with rendering)."""

    out: Path
    frames: int
    width: int
    height: int
    fps: float
    seconds: float
    points: int
    render_seconds: float = 0.0
    encoder_wait_seconds: float = 0.0

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("inf")


def render_frames(
    renderer: Renderer,
    cameras: Iterable[Camera],
    out: Path | str,
    fps: float = 30.0,
    total: int | None = None,
    progress: ProgressFn | None = None,
    cancel: CancelFn | None = None,
    encoder: EncoderOptions | None = None,
) -> RenderResult:
    """Render each camera to ``out`` (MP4 or PNG folder); ``cancel`` is checked before every frame.

    Each frame is drawn straight into a buffer the sink lends (:meth:`FrameSink.buffer`) and
    encoded on the sink's own thread and ffmpeg's while the next one renders."""
    import time

    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    sink = FrameSink(out, renderer.width, renderer.height, fps, encoder)
    start = time.perf_counter()
    drawing = 0.0
    try:
        for camera in cameras:
            if cancel is not None and cancel():
                raise RenderCancelledError(f"{out}: render cancelled after {sink.count} frame(s)")
            image = sink.buffer()
            began = time.perf_counter()
            renderer.render(camera, image)
            drawing += time.perf_counter() - began
            sink.write(image)
            if progress is not None:
                progress(sink.count, total or sink.count)
        if sink.count == 0:
            raise Slam6dError(f"{out}: the camera path produced no frames")
        path = sink.commit()
    except BaseException:
        sink.discard()
        raise
    return RenderResult(
        path,
        sink.count,
        renderer.width,
        renderer.height,
        fps,
        time.perf_counter() - start,
        len(renderer.scene),
        drawing,
        sink.wait_seconds,
    )


def render_fly_through(
    scene: PointScene,
    out: Path | str,
    width: int = 1280,
    height: int = 720,
    fps: float = 30.0,
    frames: int | None = None,
    path: CameraPath | None = None,
    options: RenderOptions | None = None,
    progress: ProgressFn | None = None,
    cancel: CancelFn | None = None,
    encoder: EncoderOptions | None = None,
) -> RenderResult:
    """The one-call fly-through: the given path, or by default one following the scan trajectory."""
    from slam6d.camera_path import trajectory_path

    if path is None:
        path = trajectory_path(scene.scan_poses, scene=scene)
    samples = path.sample(frames=frames, fps=fps)
    renderer = Renderer(scene, width, height, options)
    cameras = (renderer.camera(pose, fov) for pose, fov in samples)
    return render_frames(renderer, cameras, out, fps, len(samples), progress, cancel, encoder)
