"""The fly-through renderer: projection, occlusion, splats, shading, colours and video output."""

from __future__ import annotations

import math
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
from typer.testing import CliRunner

from slam6d.errors import Slam6dError
from slam6d.geometry import look_at, make_pose, rot_z
from slam6d.point_scene import load_render_input, point_colors, scan_palette, scene_from_points, scene_from_sequence
from slam6d.render import Camera, RenderCancelledError, Renderer, RenderOptions, render_fly_through, render_frames
from slam6d.scan import Scan, ScanSequence

PLAIN = RenderOptions(shading="none", point_size=0.0, color_mode="scan")


def forward_camera(width: int = 200, height: int = 100, fov: float = 90.0, eye=(0.0, 0.0, 0.0)) -> Camera:
    """A camera at ``eye`` looking along world +x, z up: image right is world -y, image down is world -z."""
    eye = np.asarray(eye, dtype=float)
    return Camera.from_fov(look_at(eye, eye + np.array([1.0, 0.0, 0.0])), width, height, fov)


def test_look_at_uses_opencv_axes() -> None:
    pose = look_at((1.0, 2.0, 3.0), (1.0, 7.0, 3.0))  # looking along +y
    np.testing.assert_allclose(pose[:3, 2], [0, 1, 0], atol=1e-12)  # z forward
    np.testing.assert_allclose(pose[:3, 1], [0, 0, -1], atol=1e-12)  # y down = world -z
    np.testing.assert_allclose(pose[:3, 0], [1, 0, 0], atol=1e-12)  # x right
    np.testing.assert_allclose(pose[:3, 3], [1, 2, 3])
    assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)
    straight_down = look_at((0, 0, 5), (0, 0, 0))  # degenerate up: still a proper rotation
    assert np.linalg.det(straight_down[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(straight_down[:3, 2], [0, 0, -1], atol=1e-12)


def test_point_lands_on_expected_pixel() -> None:
    camera = forward_camera()  # fx = fy = 50, cx = 100, cy = 50
    assert (camera.fx, camera.cx, camera.cy) == pytest.approx((50.0, 100.0, 50.0))
    # camera frame: x = -y_w = 1, y = -z_w = -0.5, z = 10  ->  u = 50 * 0.1 + 100 = 105, v = 50 * -0.05 + 50 = 47.5
    world = np.array([[10.0, -1.0, 0.5]])
    uv, depth = camera.project(world)
    np.testing.assert_allclose(uv[0], [105.0, 47.5])
    assert depth[0] == pytest.approx(10.0)
    renderer = Renderer(scene_from_points(world), 200, 100, PLAIN)
    depth_img, index = renderer.rasterize(camera)
    hit = np.argwhere(index >= 0)
    assert hit.tolist() == [[47, 105]]
    assert depth_img[47, 105] == pytest.approx(10.0, abs=1e-4)
    image = renderer.render(camera)
    np.testing.assert_array_equal(image[47, 105], scan_palette(1)[0])
    background = np.array(PLAIN.background, dtype=np.uint8)
    assert (image.reshape(-1, 3) == background).all(axis=1).sum() == 200 * 100 - 1


def test_far_from_origin_coordinates_keep_pixel_accuracy() -> None:
    """UTM-sized coordinates: points are stored relative to the scene origin, so float32 does not blur them."""
    offset = np.array([512_345.25, 5_412_678.5, 312.0])
    camera = forward_camera(eye=offset)
    world = offset + np.array([[10.0, -1.0, 0.5], [30.0, 2.0, -1.0]])
    renderer = Renderer(scene_from_points(world), 200, 100, PLAIN)
    _, index = renderer.rasterize(camera)
    uv, _ = camera.project(world)
    for u, v in uv:
        assert index[int(v), int(u)] >= 0


@pytest.mark.parametrize("near_first", [True, False])
def test_nearer_point_hides_farther_one(near_first: bool) -> None:
    near, far = [5.0, 0.5, 0.25], [10.0, 1.0, 0.5]  # the same ray from the origin
    points = np.array([near, far] if near_first else [far, near])
    scan = np.array([0, 1] if near_first else [1, 0])
    renderer = Renderer(scene_from_points(points, scan_index=scan), 200, 100, PLAIN)
    camera = forward_camera()
    image = renderer.render(camera)
    hits = np.argwhere(renderer.index >= 0)
    assert len(hits) == 1
    row, col = hits[0]
    assert renderer.depth[row, col] == pytest.approx(5.0, abs=1e-4)
    np.testing.assert_array_equal(image[row, col], scan_palette(2)[0])


def test_zbuffer_matches_a_reference_on_random_points() -> None:
    """Every pixel holds the nearest of the points projecting into it, whichever thread drew them."""
    rng = np.random.default_rng(3)
    points = rng.uniform([-5, -20, -10], [40, 20, 10], size=(50_000, 3))
    scene = scene_from_points(points)
    camera = Camera.from_fov(look_at((-8.0, 1.0, 2.0), (20.0, -2.0, 0.0)), 160, 120, 70.0)
    depth, index = Renderer(scene, 160, 120, PLAIN).rasterize(camera)
    uv, z = camera.project(scene.world_points())
    ok = (z > PLAIN.near) & (uv[:, 0] >= 0) & (uv[:, 0] < 160) & (uv[:, 1] >= 0) & (uv[:, 1] < 120)
    flat = uv[ok, 1].astype(int) * 160 + uv[ok, 0].astype(int)
    expected = np.full(160 * 120, np.inf)
    np.minimum.at(expected, flat, z[ok])
    np.testing.assert_allclose(depth.ravel(), expected, atol=2e-5)
    filled = np.isfinite(expected)
    np.testing.assert_allclose(z[index.ravel()[filled]], expected[filled], atol=2e-5)
    assert (index.ravel()[~filled] == -1).all()


def test_splat_size_follows_distance() -> None:
    camera = forward_camera(400, 200, 90.0)  # fx = 100
    options = RenderOptions(shading="none", point_size=0.1, max_splat=20)

    def covered(distance: float) -> int:
        renderer = Renderer(scene_from_points([[distance, 0.0, 0.0]]), 400, 200, options)
        return int((renderer.rasterize(camera)[1] >= 0).sum())

    assert covered(1.0) == 10 * 10  # 0.1 m at 1 m with fx = 100: 10 px square
    assert covered(2.0) == 5 * 5
    assert covered(50.0) == 1  # never smaller than one pixel
    assert covered(0.2) == 20 * 20  # capped at max_splat


def test_empty_view_and_empty_scene_render_background() -> None:
    background = (5, 6, 7)
    options = RenderOptions(background=background)
    behind = scene_from_points([[-3.0, 0.0, 0.0], [-10.0, 1.0, 1.0]])
    for scene in (behind, scene_from_points(np.zeros((0, 3)))):
        renderer = Renderer(scene, 64, 48, options)
        image = renderer.render(Camera.from_fov(look_at((0, 0, 0), (1, 0, 0)), 64, 48))
        assert image.shape == (48, 64, 3)
        assert (image == np.array(background, dtype=np.uint8)).all()


def test_eye_dome_lighting_darkens_depth_edges_only() -> None:
    """A near square in front of a far wall: wall pixels beside the square's outline darken, open wall does not."""
    ys, zs = np.meshgrid(np.linspace(-6, 6, 400), np.linspace(-4, 4, 300))
    wall = np.stack([np.full(ys.size, 10.0), ys.ravel(), zs.ravel()], axis=1)
    ys2, zs2 = np.meshgrid(np.linspace(-0.5, 0.5, 60), np.linspace(-0.5, 0.5, 60))
    square = np.stack([np.full(ys2.size, 4.0), ys2.ravel(), zs2.ravel()], axis=1)
    scene = scene_from_points(np.concatenate([wall, square]))
    camera = forward_camera(200, 100, 60.0)
    opts = {"color_mode": "white", "point_size": 0.08}
    lit = Renderer(scene, 200, 100, RenderOptions(shading="edl", **opts)).render(camera).astype(int)
    flat = Renderer(scene, 200, 100, RenderOptions(shading="none", **opts)).render(camera).astype(int)
    renderer = Renderer(scene, 200, 100, RenderOptions(shading="none", **opts))
    depth, _ = renderer.rasterize(camera)
    near = depth < 5.0
    border = np.zeros_like(near)
    border[1:-1, 1:-1] = ~near[1:-1, 1:-1] & (near[:-2, 1:-1] | near[2:, 1:-1] | near[1:-1, :-2] | near[1:-1, 2:])
    assert near.sum() > 50 and border.sum() > 20
    assert (lit[border].mean(axis=1) < flat[border].mean(axis=1) - 40).all()
    assert np.abs(lit[near] - flat[near]).max() <= 1
    assert np.abs(lit[5:15, 5:15] - flat[5:15, 5:15]).max() <= 1  # open wall, away from any edge


def test_depth_fog_fades_far_points_towards_background() -> None:
    points = np.array([[3.0, 0.5, 0.0], [30.0, -5.0, 0.0]])
    options = RenderOptions(
        shading="depth", color_mode="white", point_size=0.0, fog_distance=10.0, background=(0, 0, 0)
    )
    renderer = Renderer(scene_from_points(points), 200, 100, options)
    image = renderer.render(forward_camera())
    uv, _ = forward_camera().project(points)
    near_px, far_px = (image[int(v), int(u)].astype(float) for u, v in uv)
    np.testing.assert_allclose(near_px, 225 * math.exp(-0.3), atol=1.0)
    np.testing.assert_allclose(far_px, 225 * math.exp(-3.0), atol=1.0)


def test_colour_modes() -> None:
    z = np.linspace(0.0, 10.0, 101)
    points = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    scene = scene_from_points(points, scan_index=np.arange(101) % 3, intensity=np.where(z < 5, np.nan, z))
    height = point_colors(scene, "height")
    low, high = height[np.argmin(scene.points[:, 2])], height[np.argmax(scene.points[:, 2])]
    assert high.astype(int).sum() > low.astype(int).sum() + 150  # yellow top, blue-violet bottom
    by_scan = point_colors(scene, "scan")
    assert len({tuple(by_scan[scene.scan_index == s][0]) for s in range(3)}) == 3
    assert (by_scan[scene.scan_index == 1] == by_scan[scene.scan_index == 1][0]).all()
    intensity = point_colors(scene, "intensity")
    missing = np.isnan(scene.intensity)
    assert (intensity[missing] == 140).all()  # no value: neutral grey, not the ramp's dark end
    brightest = intensity[np.nanargmax(scene.intensity)]
    darkest = intensity[np.nanargmin(scene.intensity)]
    assert int(brightest.sum()) > int(darkest.sum()) + 300
    with pytest.raises(Slam6dError, match="no intensity"):
        point_colors(scene_from_points(points), "intensity")
    with pytest.raises(ValueError, match="colour mode"):
        RenderOptions(color_mode="rainbow")


def _two_scan_sequence(points_per_scan: int = 10_000) -> ScanSequence:
    rng = np.random.default_rng(0)
    scans = []
    for i, yaw in enumerate((0.0, math.pi / 2)):
        pts = rng.uniform([2, -3, -1], [12, 3, 2], size=(points_per_scan, 3))
        scans.append(Scan(pts, make_pose(rot_z(yaw), [i * 2.0, 0.0, 0.0]), name=f"scan{i:03d}", has_pose=True))
    return ScanSequence(scans)


def test_scene_from_sequence_applies_poses_and_thins_evenly() -> None:
    sequence = _two_scan_sequence()
    scene = scene_from_sequence(sequence, max_points=5_000)
    assert 4_500 < len(scene) < 5_500
    assert scene.total_points == 20_000
    counts = np.bincount(scene.scan_index)
    assert abs(int(counts[0]) - int(counts[1])) < 400
    world = scene.world_points()
    second = world[scene.scan_index == 1]  # rotated 90° about z and moved 2 m along x
    assert second[:, 1].min() > 2.0 - 1e-4 and second[:, 0].min() > 2.0 - 3.0 - 1e-4
    np.testing.assert_allclose(scene.scan_positions, [[0, 0, 0], [2, 0, 0]])
    assert len(scene_from_sequence(sequence, max_points=None)) == 20_000


def _read_video(path: Path) -> tuple[tuple[int, int], int]:
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    count = sum(1 for _ in reader)
    return tuple(meta["size"]), count


def test_video_has_requested_frames_and_size(tmp_path: Path) -> None:
    scene = scene_from_sequence(_two_scan_sequence(2_000))
    progress: list[tuple[int, int]] = []
    result = render_fly_through(
        scene, tmp_path / "fly.mp4", 96, 64, fps=12, frames=17, progress=lambda d, t: progress.append((d, t))
    )
    assert result.frames == 17 and result.out == tmp_path / "fly.mp4"
    assert _read_video(tmp_path / "fly.mp4") == ((96, 64), 17)
    assert progress[-1] == (17, 17) and [d for d, _ in progress] == list(range(1, 18))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fly.mp4"]  # no temporary leftovers


def test_png_frames_and_odd_sizes(tmp_path: Path) -> None:
    scene = scene_from_sequence(_two_scan_sequence(2_000))
    render_fly_through(scene, tmp_path / "frames", 33, 21, frames=3)
    from PIL import Image

    names = sorted(p.name for p in (tmp_path / "frames").iterdir())
    assert names == ["frame_000000.png", "frame_000001.png", "frame_000002.png"]
    assert Image.open(tmp_path / "frames" / names[0]).size == (33, 21)
    with pytest.raises(Slam6dError, match="even width and height"):
        render_fly_through(scene, tmp_path / "odd.mp4", 33, 21, frames=3)
    with pytest.raises(Slam6dError, match=r"\.mp4 file or a directory"):
        render_fly_through(scene, tmp_path / "fly.gif", 32, 20, frames=3)


def test_cancel_stops_between_frames_and_leaves_nothing(tmp_path: Path) -> None:
    scene = scene_from_sequence(_two_scan_sequence(2_000))
    renderer = Renderer(scene, 64, 48)
    cameras = [renderer.camera(look_at((0, 0, 1), (10, k * 0.1, 0))) for k in range(20)]
    done: list[int] = []
    with pytest.raises(RenderCancelledError, match="after 3 frame"):
        render_frames(renderer, cameras, tmp_path / "fly.mp4", progress=lambda d, t: done.append(d),
                      cancel=lambda: len(done) >= 3)  # fmt: skip
    assert done == [1, 2, 3]
    assert list(tmp_path.iterdir()) == []


def _write_uos_dir(folder: Path) -> None:
    from slam6d.geometry import UOS
    from slam6d.io.uos import write_uos_scan

    folder.mkdir()
    for i, scan in enumerate(_two_scan_sequence(3_000)):
        write_uos_scan(folder, i, UOS.points_to_native(scan.points), UOS.pose_to_native(scan.pose))


def test_cli_render_scan_directory_with_saved_path(tmp_path: Path) -> None:
    from slam6d.cli import app

    _write_uos_dir(tmp_path / "scans")
    runner = CliRunner()
    out = tmp_path / "fly.mp4"
    args = ["render", str(tmp_path / "scans"), "--out", str(out), "--size", "80x60", "--frames", "6"]
    result = runner.invoke(app, [*args, "--save-path", str(tmp_path / "path.json"), "--max-points", "4000"])
    assert result.exit_code == 0, result.output
    assert _read_video(out) == ((80, 60), 6)
    assert "6 frames 80x60" in result.output
    result = runner.invoke(app, [*args[:3], str(tmp_path / "again.mp4"), "--size", "64x48", "--path",
                                 str(tmp_path / "path.json"), "--color", "scan"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert _read_video(tmp_path / "again.mp4")[0] == (64, 48)
    bad = runner.invoke(app, [*args, "--size", "big"])
    assert bad.exit_code != 0 and "1280x720" in bad.output


def test_load_render_input_reads_scans_with_their_poses(tmp_path: Path) -> None:
    _write_uos_dir(tmp_path / "scans")
    scene, saved = load_render_input(tmp_path / "scans", max_points=None)
    assert saved is None and len(scene) == 6_000
    np.testing.assert_allclose(scene.scan_positions, [[0, 0, 0], [2, 0, 0]], atol=1e-6)


@pytest.mark.slow
def test_kurt3d_frame_reads_as_a_scene(shared_data: Path, artifacts_dir: Path) -> None:
    """A real map from the default path: most of the frame is covered and EDL gives it visible structure."""
    from slam6d.camera_path import trajectory_path

    scene, _ = load_render_input(shared_data / "kurt3d_3dtk")
    pose, fov = trajectory_path(scene.scan_poses).sample(frames=10)[3]
    renderer = Renderer(scene, 320, 180, RenderOptions(color_mode="white"))
    image = renderer.render(renderer.camera(pose, fov))
    covered = (renderer.index >= 0).mean()
    assert covered > 0.6
    grey = image[renderer.index >= 0].mean(axis=1)
    assert grey.std() > 20  # shading varies: not a flat silhouette


def test_overlapped_encoding_writes_every_frame_in_order(tmp_path: Path) -> None:
    """Frames go to the encoder on a writer thread, from copies: the caller may reuse its buffer at once."""
    import imageio_ffmpeg

    from slam6d.video import FrameSink

    sink = FrameSink(tmp_path / "grey.mp4", 64, 48, fps=10)
    image = np.empty((48, 64, 3), dtype=np.uint8)
    levels = [(37 * k) % 250 for k in range(25)]
    for level in levels:
        image[:] = level  # the same buffer every frame, as the renderer does
        sink.write(image)
    sink.commit()
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "grey.mp4"))
    meta = next(reader)
    read = [float(np.frombuffer(frame, dtype=np.uint8).mean()) for frame in reader]
    assert tuple(meta["size"]) == (64, 48)
    np.testing.assert_allclose(read, levels, atol=3)  # H.264 of flat grey: within a few levels


def test_encoder_failure_is_raised_and_leaves_nothing(tmp_path: Path) -> None:
    from slam6d.video import FrameSink

    class Broken:
        def send(self, frame: object) -> None:
            raise BrokenPipeError("ffmpeg exited")

        def close(self) -> None:
            pass

    sink = FrameSink(tmp_path / "fly.mp4", 64, 48, fps=10)
    real = sink._writer
    sink._writer = Broken()
    with pytest.raises(Slam6dError, match="encoder failed: ffmpeg exited"):
        for _ in range(50):
            sink.write(np.zeros((48, 64, 3), dtype=np.uint8))
        sink.commit()
    sink._writer = real
    sink.discard()
    assert list(tmp_path.iterdir()) == []


def test_a_stored_map_streams_into_the_scene_the_sequence_gives(tmp_path: Path) -> None:
    """`slam6d render OUT/scan_store --poses OUT/poses_kitti.txt`: the map is read one scan at a time
    within the store's budget and thinned as the in-memory sequence would be."""
    from slam6d.geometry import UOS
    from slam6d.io.poses import write_kitti_poses
    from slam6d.point_scene import scene_from_store
    from slam6d.scan_store import ScanStore

    sequence = _two_scan_sequence(20_000)
    for scan in sequence:
        scan.points = scan.points.astype(np.float32).astype(np.float64)
    directory = ScanStore.create(tmp_path / "scan_store", [Scan(s.points, np.eye(4), s.name) for s in sequence], UOS)
    write_kitti_poses(tmp_path / "poses.txt", [UOS.pose_to_native(s.pose) for s in sequence])
    want = scene_from_sequence(sequence, max_points=10_000)
    got, path = load_render_input(directory, poses_file=tmp_path / "poses.txt", max_points=10_000)
    assert path is None and got.total_points == 40_000 and len(got) == len(want)
    np.testing.assert_allclose(got.world_points(), want.world_points(), atol=1e-4)
    np.testing.assert_array_equal(got.scan_index, want.scan_index)
    store = ScanStore(directory, budget=20_000 * 24)  # one scan's cloud at a time
    scene_from_store(store, [s.pose for s in sequence], max_points=10_000)
    assert store.peak_bytes <= store.budget and store.loads == 2
    with pytest.raises(Slam6dError, match="1 poses for 2 stored scans"):
        scene_from_store(store, [np.eye(4)])


def test_lent_buffers_reach_the_encoder_uncopied_and_in_order(tmp_path: Path) -> None:
    """Frames drawn into the sink's own buffers are encoded as they are, in order, from a fixed pool
    (no allocation or copy per frame), however far the renderer runs ahead of the encoder."""
    from slam6d.video import FrameSink

    sink = FrameSink(tmp_path / "grey.mp4", 64, 48, fps=10)
    levels = [(53 * k) % 250 for k in range(30)]
    lent = set()
    for level in levels:
        image = sink.buffer()
        lent.add(id(image))
        image[:] = level
        sink.write(image)
    sink.commit()
    assert len(lent) <= FrameSink.QUEUED + 1
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "grey.mp4"))
    next(reader)
    read = [float(np.frombuffer(frame, dtype=np.uint8).mean()) for frame in reader]
    np.testing.assert_allclose(read, levels, atol=3)


def test_written_frames_are_the_renderers_frames(tmp_path: Path) -> None:
    """The frames a render writes are exactly what the renderer draws for each camera (PNG: lossless)."""
    from PIL import Image

    scene = scene_from_sequence(_two_scan_sequence(3_000))
    renderer = Renderer(scene, 64, 48)
    cameras = [renderer.camera(look_at((0, 0, 1), (10, k * 0.3 - 1.5, 0))) for k in range(8)]
    render_frames(renderer, cameras, tmp_path / "frames")
    written = [np.asarray(Image.open(p)) for p in sorted((tmp_path / "frames").iterdir())]
    assert len(written) == len(cameras)
    for image, camera in zip(written, cameras, strict=True):
        np.testing.assert_array_equal(image, renderer.render(camera))


def test_encoder_options_are_checked_and_named() -> None:
    from slam6d.cli import app
    from slam6d.video import EncoderOptions

    with pytest.raises(ValueError, match=r"unknown x264 preset 'quick'.*ultrafast"):
        EncoderOptions(preset="quick")
    with pytest.raises(ValueError, match=r"crf must be within 0\.\.51"):
        EncoderOptions(crf=60)
    bad = CliRunner().invoke(app, ["render", "nowhere", "--preset", "quick"])
    assert bad.exit_code != 0 and "ultrafast" in bad.output


def test_a_session_renders_streamed_from_its_level_store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`slam6d render SESSION` reads only the points it draws from the session's cache: the first time
    builds the level store, every later render reads a prefix of each scan and no full scan; the frame
    shows the same map as the in-memory sequence's."""
    from slam6d.session import Session

    _write_uos_dir(tmp_path / "scans")
    session = Session.create(tmp_path / "session", "Two", tmp_path / "scans")
    first, _ = load_render_input(session.folder, max_points=2_000)
    sequence = session.load_sequence()

    def no_full_read(*args: object, **kwargs: object) -> None:
        raise AssertionError("the streamed render read the whole session")

    monkeypatch.setattr(Session, "load_sequence", no_full_read)
    scene, _ = load_render_input(session.folder, max_points=2_000)
    assert len(scene) == len(first) == 2_000 and scene.total_points == 6_000
    assert scene.read_bytes == len(scene) * 3 * 4  # float32 xyz of the points drawn, nothing more
    np.testing.assert_array_equal(np.bincount(scene.scan_index), [1_000, 1_000])
    np.testing.assert_allclose(scene.scan_positions, [[0, 0, 0], [2, 0, 0]], atol=1e-6)
    # an even spatial sample: the streamed map fills the same box as the whole one
    whole = scene_from_sequence(sequence, max_points=None)
    lo, hi = whole.bounds()
    got_lo, got_hi = scene.bounds()
    np.testing.assert_allclose(got_lo, lo, atol=0.5)
    np.testing.assert_allclose(got_hi, hi, atol=0.5)
    # and looks the same from a camera as the random sample of the in-memory path
    camera = Camera.from_fov(look_at((0, 0, 1), (10, 0, 0)), 96, 64)
    options = RenderOptions(point_size=0.2)
    streamed = Renderer(scene, 96, 64, options)
    streamed.render(camera)
    in_memory = Renderer(scene_from_sequence(sequence, max_points=2_000), 96, 64, options)
    in_memory.render(camera)
    assert abs(float((streamed.index >= 0).mean()) - float((in_memory.index >= 0).mean())) < 0.05
    # the scans are volumes of scattered points, so single pixels differ; the depth they show does not
    typical = [float(np.median(r.depth[np.isfinite(r.depth)])) for r in (streamed, in_memory)]
    assert typical[0] == pytest.approx(typical[1], rel=0.1)
