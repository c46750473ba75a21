"""Fly-through rendering speed: frames per second of the numba renderer against a plain numpy z-buffer.

    .venv/bin/python benchmarks/render.py            # synthetic hall, 1280x720/2M and 640x480/1M
    .venv/bin/python benchmarks/render.py --balm     # also the real BALM hall map (needs ../shared/data)
    .venv/bin/python benchmarks/render.py --video    # also end-to-end MP4 encoding
    .venv/bin/python benchmarks/render.py --campus /tmp/campus1000   # `slam6d render` on a 1,000-scan session
    .venv/bin/python benchmarks/render.py --encoders # x264 presets: CPU, size, PSNR on rendered frames

Frames are rendered along a camera path through the scene, so every frame sees a different mix of
near (large splat) and far points. The machine may be shared: each figure is the best of several
passes over the path (the least disturbed one) with the median pass alongside.

End to end (``--video`` with ``--balm``, ``--campus``) means the `slam6d render` command itself, run
as its own process: start-up, reading the map, rendering and H.264 encoding until the MP4 is in
place. Its CPU time (with ffmpeg's) is printed beside the wall time: on a shared machine the wall
time measures the other processes too, while CPU ms per frame says what 2 idle cores would do.
``--campus DIR`` takes the scans of ``slam6d simulate DIR --world campus --scans 1000
--points-per-scan 20000 --seed 3``, makes a session over them (in a temporary folder) and opens it
once, as the workbench would, so that its caches exist; the render then streams from them.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

# what `slam6d` and the workbench do at start (see slam6d.cli.main); override by setting it
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from slam6d.camera_path import CameraPath, Keyframe, trajectory_path  # noqa: E402
from slam6d.point_scene import PointScene, point_colors, scene_from_points  # noqa: E402
from slam6d.render import Camera, Renderer, RenderOptions, render_frames  # noqa: E402


def synthetic_hall(n: int, seed: int = 0) -> PointScene:
    """A 40 x 20 x 6 m hall: floor, ceiling, walls and a few boxes, points spread evenly over the surfaces."""
    rng = np.random.default_rng(seed)
    parts = []
    surfaces = [  # (weight, sampler)
        (0.35, lambda k: np.c_[rng.uniform(0, 40, k), rng.uniform(0, 20, k), np.zeros(k)]),
        (0.2, lambda k: np.c_[rng.uniform(0, 40, k), rng.uniform(0, 20, k), np.full(k, 6.0)]),
        (0.15, lambda k: np.c_[rng.uniform(0, 40, k), rng.choice([0.0, 20.0], k), rng.uniform(0, 6, k)]),
        (0.1, lambda k: np.c_[rng.choice([0.0, 40.0], k), rng.uniform(0, 20, k), rng.uniform(0, 6, k)]),
    ]
    for weight, sample in surfaces:
        parts.append(sample(int(n * weight)))
    boxes = n - sum(len(p) for p in parts)
    centres = rng.uniform([3, 3, 0], [37, 17, 0], size=(12, 3))
    which = rng.integers(0, len(centres), boxes)
    offsets = rng.uniform(-1.0, 1.0, size=(boxes, 3))
    face = rng.integers(0, 3, boxes)
    offsets[np.arange(boxes), face] = np.sign(offsets[np.arange(boxes), face])  # points on the box surfaces
    parts.append(centres[which] + offsets * [1.0, 1.0, 1.0] + [0.0, 0.0, 1.0])
    points = np.concatenate(parts)
    return scene_from_points(points, scan_index=rng.integers(0, 40, len(points)))


def hall_path(scene: PointScene) -> CameraPath:
    lo, hi = scene.bounds()
    mid_y, z = (lo[1] + hi[1]) / 2, lo[2] + 1.6
    ends = [lo[0] + 2.0, hi[0] - 2.0]
    keys = [
        Keyframe.looking_at([ends[0], mid_y - 3, z], [hi[0], mid_y, z - 0.5]),
        Keyframe.looking_at([(ends[0] + ends[1]) / 2, mid_y + 2, z], [hi[0], mid_y - 4, z - 0.5]),
        Keyframe.looking_at([ends[1], mid_y, z], [hi[0] + 5, mid_y + 6, z]),
    ]
    return CameraPath(keys)


def numpy_zbuffer(points: np.ndarray, colors: np.ndarray, camera: Camera) -> np.ndarray:
    """The plain numpy baseline: project, sort far-to-near, scatter (the last, nearest write wins)."""
    inv = np.linalg.inv(camera.pose)
    pc = points @ inv[:3, :3].T.astype(np.float32) + inv[:3, 3].astype(np.float32)
    z = pc[:, 2]
    front = z > 0.05
    pc, z, col = pc[front], z[front], colors[front]
    u = (camera.fx * pc[:, 0] / z + camera.cx).astype(np.int32)
    v = (camera.fy * pc[:, 1] / z + camera.cy).astype(np.int32)
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    order = np.argsort(-z[inside], kind="stable")
    image = np.zeros((camera.height, camera.width, 3), dtype=np.uint8)
    image[v[inside][order], u[inside][order]] = col[inside][order]
    return image


def measure(render_one: Callable[[Camera], object], cameras: list[Camera], passes: int) -> tuple[float, float, float]:
    """(best, median) frames per second over ``passes`` runs along the path, and the least CPU ms per frame.

    CPU time (all threads) is the figure least disturbed by other processes on a shared machine.
    """
    render_one(cameras[0])  # compile / warm caches
    rates, cpu = [], []
    for _ in range(passes):
        start, cpu_start = time.perf_counter(), time.process_time()
        for camera in cameras:
            render_one(camera)
        rates.append(len(cameras) / (time.perf_counter() - start))
        cpu.append((time.process_time() - cpu_start) / len(cameras) * 1000.0)
    return max(rates), statistics.median(rates), min(cpu)


def bench(
    scene: PointScene, label: str, width: int, height: int, frames: int, passes: int, baseline: bool, path: CameraPath
) -> None:
    renderer = Renderer(scene, width, height, RenderOptions())
    cameras = [renderer.camera(pose, fov) for pose, fov in path.sample(frames=frames)]
    image = np.empty((height, width, 3), dtype=np.uint8)
    best, median, cpu = measure(lambda cam: renderer.render(cam, image), cameras, passes)
    covered = float((renderer.index >= 0).mean())
    size = f"{width}x{height} {len(scene) / 1e6:3.1f}M"
    print(f"{label:28s} {size}  numba: {best:6.1f} fps (median {median:5.1f}, {cpu:5.1f} CPU ms/frame)", end="")
    if baseline:
        colors = point_colors(scene, "height")
        b_best, b_median, b_cpu = measure(lambda cam: numpy_zbuffer(scene.points, colors, cam), cameras, passes)
        print(f"  numpy z-buffer: {b_best:5.1f} fps (median {b_median:5.1f}, {b_cpu:5.1f} CPU ms/frame)", end="")
    print(f"  [{covered:.0%} of pixels covered]")


def bench_video(scene: PointScene, width: int, height: int, frames: int, preset: str) -> None:
    """Render and encode in this process (no start-up, no map reading): the streaming rate alone."""
    from slam6d.video import EncoderOptions

    renderer = Renderer(scene, width, height, RenderOptions())
    cameras = [renderer.camera(pose, fov) for pose, fov in hall_path(scene).sample(frames=frames)]
    renderer.render(cameras[0])
    with tempfile.TemporaryDirectory() as tmp:
        result = render_frames(renderer, cameras, Path(tmp) / "bench.mp4", 30, encoder=EncoderOptions(preset=preset))
    print(
        f"{'render + MP4 in process':28s} {width}x{height} {len(scene) / 1e6:4.1f}M  {result.frames_per_second:6.1f} fps"
        f"  (drawing {result.render_seconds / result.frames * 1e3:.1f} ms/frame, waiting for x264 {preset}"
        f" {result.encoder_wait_seconds / result.frames * 1e3:.1f} ms/frame)"
    )


def bench_encoders(scene: PointScene, frames: int) -> None:
    """x264 presets on the same rendered frames: ffmpeg's CPU per frame (its RGB -> YUV conversion
    included), the file size and the PSNR of the decoded frames against the rendered ones."""
    import imageio_ffmpeg

    renderer = Renderer(scene, 1280, 720, RenderOptions())
    images = [renderer.render(renderer.camera(p, f)).copy() for p, f in hall_path(scene).sample(frames=frames)]
    with tempfile.TemporaryDirectory() as tmp:
        for preset in ("ultrafast", "superfast", "veryfast"):
            out = Path(tmp) / f"{preset}.mp4"
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            command = [imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24"]
            command += ["-s", "1280x720", "-r", "30", "-i", "-", "-c:v", "libx264", "-preset", preset, "-crf", "23"]
            encoder = subprocess.Popen([*command, "-pix_fmt", "yuv420p", str(out)], stdin=subprocess.PIPE)
            assert encoder.stdin is not None
            for image in images:
                encoder.stdin.write(image.data)  # the array itself, not a copy
            encoder.stdin.close()
            encoder.wait()
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            reader = imageio_ffmpeg.read_frames(str(out))
            next(reader)
            errors = [
                np.mean((np.frombuffer(b, np.uint8).reshape(image.shape).astype(np.float64) - image) ** 2)
                for b, image in zip(reader, images, strict=True)
            ]
            print(
                f"{'x264 ' + preset + ', crf 23':28s} 1280x720  {cpu / frames * 1e3:5.1f} CPU ms/frame,"
                f" {out.stat().st_size / frames / 1e3:5.0f} kB/frame, PSNR {10 * np.log10(255**2 / np.mean(errors)):.1f} dB"
            )


def cli_render(label: str, args: list[str], frames: int, preset: str) -> None:
    """`slam6d render ARGS` as its own process, 1280x720, timed from launch to the MP4 in place."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "slam6d.cli", "render", *args, "--out", f"{tmp}/fly.mp4"]
        command += ["--size", "1280x720", "--frames", str(frames), "--preset", preset]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the CLI and its ffmpeg, both waited for
    if done.returncode != 0:
        raise SystemExit(f"{label}: slam6d render failed:\n{done.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    patterns = {
        "streaming": r"\(([0-9.]+) frames/s rendered and encoded",
        "start_up": r"start-up ([0-9.]+) CPU s",
        "memory": r"peak memory (\d+) MB",
        "points": r"([0-9,]+ of [0-9,]+ points)",
        "read": r"\d+ scans(, \d+ MB read|)",
    }
    text: dict[str, str] = {}
    for key, pattern in patterns.items():
        match = re.search(pattern, done.stdout + done.stderr)
        if match is None:
            raise SystemExit(f"{label}: no {key} in the output of slam6d render:\n{done.stdout}\n{done.stderr[-2000:]}")
        text[key] = match.group(1)
    start_up = float(text["start_up"])
    per_frame = (cpu - start_up) / frames * 1e3  # the render process's threads and ffmpeg's
    # what 2 idle cores would do: start-up runs mostly on one core, frames on both
    idle = frames / (start_up + frames * per_frame / 2000.0)
    print(
        f"{label:28s} 1280x720 {text['points']}{text['read']}: {frames / wall:5.1f} fps end to end ({frames} frames in"
        f" {wall:.1f} s with start-up), {text['streaming']} fps rendering + encoding; CPU: start-up {start_up:.1f} s,"
        f" {per_frame:.0f} ms/frame with x264 {preset} -> {2000.0 / per_frame:.0f} fps streaming,"
        f" {idle:.0f} fps end to end on 2 idle cores; peak memory {text['memory']} MB; load {os.getloadavg()[0]:.1f}"
    )


def campus_session(scans: Path, folder: Path) -> Path:
    """A session over the simulated campus, opened once so its scan cache and level store exist."""
    from slam6d.point_scene import load_render_input
    from slam6d.session import Session

    start = time.perf_counter()
    Session.create(folder, "campus", scans)
    load_render_input(folder)
    print(f"{'campus: first open':28s} {time.perf_counter() - start:5.1f} s (parses the scans, builds the caches once)")
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60, help="frames per pass along the path")
    parser.add_argument("--passes", type=int, default=5)
    parser.add_argument("--balm", action="store_true", help="also render the real BALM hall map")
    parser.add_argument("--video", action="store_true", help="also measure end-to-end MP4 writing")
    parser.add_argument("--campus", type=Path, help="scans of a simulated campus: `slam6d render` on a session of them")
    parser.add_argument("--video-frames", type=int, default=300, help="frames of each end-to-end MP4 (300: 10 s)")
    parser.add_argument("--preset", default="ultrafast", help="x264 preset of the MP4 runs")
    parser.add_argument("--encoders", action="store_true", help="compare x264 presets on the same rendered frames")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min) at the start")
    print(f"numba {numba.__version__}, {numba.get_num_threads()} threads, threading layer ", end="")
    hall2m, hall1m = synthetic_hall(2_000_000), synthetic_hall(1_000_000)
    Renderer(hall1m, 8, 8).render(Camera.from_fov(np.eye(4), 8, 8))
    print(numba.threading_layer())
    bench(hall2m, "synthetic hall", 1280, 720, args.frames, args.passes, True, hall_path(hall2m))
    bench(hall1m, "synthetic hall", 640, 480, args.frames, args.passes, True, hall_path(hall1m))
    data = ROOT.parent / "shared" / "data" / "balm_hall"
    if args.balm:
        from slam6d.point_scene import load_render_input

        scene, _ = load_render_input(
            data / "velodyne_style_bin", poses_file=data / "poses_subset_kitti3x4.txt", max_points=2_000_000
        )
        path = trajectory_path(scene.scan_poses)  # the default fly-through path of `slam6d render`
        bench(scene, "BALM hall (real, 89 scans)", 1280, 720, args.frames, args.passes, False, path)
    if args.video:
        bench_video(hall2m, 1280, 720, 150, args.preset)
        if args.balm:
            balm = [str(data / "velodyne_style_bin"), "--poses", str(data / "poses_subset_kitti3x4.txt")]
            cli_render("BALM hall: slam6d render", balm, args.video_frames, args.preset)
    if args.encoders:
        bench_encoders(hall2m, args.frames)
    if args.campus:
        with tempfile.TemporaryDirectory() as tmp:
            session = campus_session(args.campus, Path(tmp) / "campus")
            cli_render(f"campus {args.campus.name}: render", [str(session)], args.video_frames, args.preset)
    print(
        f"load average {os.getloadavg()[0]:.2f} (1 min) at the end; OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}"
    )


if __name__ == "__main__":
    main()
