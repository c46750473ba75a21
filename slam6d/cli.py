"""The ``slam6d`` command line: thin wrappers that parse options and call the engine."""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import typer

from slam6d.errors import Slam6dError

if TYPE_CHECKING:
    from rich.console import Console

# Set before numpy loads OpenBLAS. The engine's BLAS calls are thin ((N, 3) by (3, 3) products); BLAS
# threads spinning between them starve the kd-tree and numba threads on a shared 2-core machine:
# reading the 46-scan benchmark loop took 8 s under load instead of 2 s, its registration twice as long.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

app = typer.Typer(add_completion=False, no_args_is_help=True, help="6D SLAM for 3D laser scans (Kurt3D method).")


class _Stderr:
    """rich's stderr console, made on first use: importing rich costs a tenth of a second that a
    command whose output goes to a file or a pipe does not need to pay."""

    _console: Console | None = None

    @property
    def console(self) -> Console:
        if _Stderr._console is None:
            from rich.console import Console

            _Stderr._console = Console(stderr=True)
        return _Stderr._console

    def __getattr__(self, name: str) -> Any:
        return getattr(self.console, name)


err = _Stderr()


@contextmanager
def progress_bar(description: str) -> Iterator[callable]:  # type: ignore[valid-type]
    """A rich progress bar on stderr; yields ``update(done, total)`` for the engine's callbacks."""
    if not sys.stderr.isatty():  # rich would draw nothing here
        yield lambda done, total: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err.console,
        transient=False,
        disable=not err.is_terminal,
    ) as progress:
        task = progress.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        yield update


FormatOption = Annotated[str | None, typer.Option("--format", "-f", help="Input format name (see `slam6d formats`).")]


@app.command()
def formats() -> None:
    """List the scan formats ``--format`` accepts."""
    from slam6d.io.registry import format_names, get_format

    for name in format_names():
        fmt = get_format(name)
        typer.echo(f"{name:10s} {' '.join(fmt.suffixes):18s} {fmt.description}")


@app.command()
def match(
    model: Annotated[Path, typer.Argument(help="Scan that stays put.")],
    data: Annotated[Path, typer.Argument(help="Scan to move onto MODEL.")],
    fmt: FormatOption = None,
    guess: Annotated[
        str,
        typer.Option(
            help="Start search before ICP: auto (octree search when poses are missing or ICP fits poorly, then the "
            "FPFH+RANSAC feature guess if that fits poorly too), octree, features, none."
        ),
    ] = "auto",
    method: Annotated[
        str, typer.Option(help="ICP minimiser: point_to_plane or point_to_point (SVD).")
    ] = "point_to_plane",
    max_distance: Annotated[float, typer.Option(help="ICP max pair distance in metres.")] = 0.25,
    iterations: Annotated[int, typer.Option(help="ICP iteration cap.")] = 50,
    voxel: Annotated[
        float | None, typer.Option(help="Reduce DATA to one real point per voxel of this size (m); 0 = all points.")
    ] = None,
    min_range: Annotated[float | None, typer.Option(help="Drop points nearer than this (files' units).")] = None,
    max_range: Annotated[float | None, typer.Option(help="Drop points farther than this (files' units).")] = None,
    trace: Annotated[Path | None, typer.Option(help="Write the octree-search and ICP trace as JSON.")] = None,
) -> None:
    """Register DATA onto MODEL; print the 4x4 transform (row-major, the files' own units) mapping DATA into MODEL."""
    from slam6d.icp import ICPConfig
    from slam6d.io.registry import ReadOptions, read_scan, resolve_format
    from slam6d.numba_blas import load_blas_bindings
    from slam6d.pair import GUESS_CHOICES, register_pair
    from slam6d.trace import write_trace

    try:
        config = ICPConfig(max_distance=max_distance, max_iterations=iterations, method=method)
        if voxel is not None:
            config = replace(config, data_voxel_size=voxel)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    if guess not in GUESS_CHOICES:
        raise typer.BadParameter(f"--guess must be one of {', '.join(GUESS_CHOICES)}, got {guess!r}")
    load_blas_bindings()  # before numba's first call: 0.15 s of scipy.linalg it never uses
    conventions = [resolve_format(path, fmt).convention for path in (model, data)]
    options = ReadOptions(min_range=min_range, max_range=max_range)
    model_scan, data_scan = (read_scan(path, fmt, options) for path in (model, data))
    result = register_pair(model_scan, data_scan, guess, config)
    # Back to native units: p_model_native = S_model^-1 · T · S_data · p_data_native.
    native = conventions[0].similarity_from_canonical() @ result.transform @ conventions[1].similarity_to_canonical()
    for row in native:
        typer.echo(" ".join(f"{value:.9g}" for value in row))
    err.print(
        f"ICP: {len(result.icp.iterations)} iterations, {result.icp.pairs} pairs, "
        f"rms {result.icp.rms * 100:.2f} cm, converged={result.icp.converged}"
    )
    if len(result.attempts) > 1 or result.winner != "start":
        tries = ", ".join(
            f"{a.source} (fitness {a.fitness:.2f})" if not a.error else f"{a.source} (failed)" for a in result.attempts
        )
        err.print(f"starts tried: {tries}; kept: {result.winner}")
    if trace is not None:
        write_trace(trace, result)


@app.command()
def render(
    source: Annotated[Path, typer.Argument(help="Session folder (with session.toml), or scan directory/file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output .mp4, or a directory for PNG frames.")] = Path(
        "fly.mp4"
    ),
    size: Annotated[str, typer.Option(help="Frame size WIDTHxHEIGHT.")] = "1280x720",
    fps: Annotated[float, typer.Option(help="Frames per second of the video.")] = 30.0,
    frames: Annotated[int | None, typer.Option(help="Number of frames (default: from path length and speed).")] = None,
    path: Annotated[Path | None, typer.Option("--path", help="Camera path JSON (default: follow the scans).")] = None,
    save_path: Annotated[Path | None, typer.Option(help="Also write the camera path used, as JSON.")] = None,
    fmt: FormatOption = None,
    poses: Annotated[Path | None, typer.Option(help="KITTI 3x4 pose file for the scans.")] = None,
    max_points: Annotated[int, typer.Option(help="Thin the map to at most this many points.")] = 2_000_000,
    color: Annotated[str, typer.Option(help="Colour: height, scan, intensity or white.")] = "height",
    shading: Annotated[str, typer.Option(help="Shading: edl, depth, edl+depth or none.")] = "edl",
    point_size: Annotated[float, typer.Option(help="Splat size in metres (pixels shrink with distance).")] = 0.03,
    height: Annotated[float, typer.Option(help="Default path: metres above the scan positions.")] = 1.0,
    speed: Annotated[float, typer.Option(help="Default path: metres per second of video.")] = 1.0,
    preset: Annotated[
        str,
        typer.Option(
            help="x264 preset: ultrafast (keeps up with the renderer on 2 cores) ... veryslow (smaller files, "
            "slower encoding; veryfast costs ~4x the CPU of ultrafast)."
        ),
    ] = "ultrafast",
    crf: Annotated[int, typer.Option(help="H.264 quality, 0-51: lower is better and larger (18 near lossless).")] = 23,
) -> None:
    """Render a fly-through video of the registered map, on the CPU (no browser or GPU needed).

    A session's map is streamed from the level-of-detail store in its cache: only the points
    drawn are read. Frames are encoded by ffmpeg while the next ones render."""
    import threading
    import time

    from slam6d.camera_path import load_camera_path, save_camera_path, trajectory_path
    from slam6d.point_scene import load_render_input
    from slam6d.render import RenderOptions, prepare_kernels, render_fly_through
    from slam6d.scan_store import peak_memory_bytes
    from slam6d.video import EncoderOptions

    try:
        width, height_px = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"--size must look like 1280x720, got {size!r}") from None
    try:
        options = RenderOptions(color_mode=color, shading=shading, point_size=point_size)
        encoder = EncoderOptions(preset=preset, crf=crf)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    warm_up = threading.Thread(target=prepare_kernels, name="kernel-warm-up", daemon=True)
    warm_up.start()  # overlaps numba's start-up with reading the map
    with progress_bar("reading scans") as update:
        scene, session_path = load_render_input(source, fmt, poses, max_points, update, color == "intensity")
    warm_up.join()
    camera_path = load_camera_path(path) if path else session_path
    if camera_path is None:
        camera_path = trajectory_path(scene.scan_poses, height=height, speed=speed)
    if save_path:
        save_camera_path(save_path, camera_path)
    streamed = f", {scene.read_bytes / 1e6:.0f} MB read from the store" if scene.read_bytes else ""
    err.print(f"{len(scene):,} of {scene.total_points:,} points, {len(scene.scan_poses)} scans{streamed}")
    start_up_cpu = time.process_time()  # this process's CPU so far (all threads): imports, reading the map
    with progress_bar("rendering") as update:
        result = render_fly_through(
            scene, out, width, height_px, fps, frames, camera_path, options, progress=update, encoder=encoder
        )
    peak_mb = peak_memory_bytes() / 1e6
    typer.echo(
        f"{result.out}: {result.frames} frames {width}x{height_px} at {fps:g} fps "
        f"({result.frames_per_second:.1f} frames/s rendered and encoded; drawing {result.render_seconds:.1f} s, "
        f"waiting for the encoder {result.encoder_wait_seconds:.1f} s; start-up {start_up_cpu:.1f} CPU s; "
        f"peak memory {peak_mb:.0f} MB)"
    )


@app.command()
def simulate(
    out: Annotated[Path, typer.Argument(help="Directory to write the uos session into.")],
    seed: Annotated[int, typer.Option(help="Random seed: the same seed writes identical files.")] = 0,
    scans: Annotated[
        int,
        typer.Option(help="Number of scans: the robot spreads them over one lap, handheld and car take a step each."),
    ] = 20,
    world: Annotated[
        str,
        typer.Option(
            help="loop (a robot's ~100 m loop round a block, the seed's world), indoor (hall, corridor, rooms "
            "with doors), outdoor (streets, 3 x 2 blocks, car scale) or campus (6 x 4 blocks, ~2.9 km of loops, "
            "a parking deck with a ramp)."
        ),
    ] = "loop",
    sensor: Annotated[
        str | None,
        typer.Option(
            help="rotating-sick (a 181-reading fan turned 360°), tilting-sick (Kurt3D's 180° front view), vlp16, "
            "hdl32, hdl64 or os1-64. Default: the world's (loop rotating-sick, indoor vlp16, outdoor hdl32, "
            "campus vlp16)."
        ),
    ] = None,
    motion: Annotated[
        str | None,
        typer.Option(
            help="robot (stop-and-go, stops spread over one lap), handheld (0.3-0.7 m steps, turns up to 45°, "
            "wobble) or car (1-3 m steps, smooth). Default: the world's (loop robot, indoor handheld, "
            "outdoor and campus car)."
        ),
    ] = None,
    points_per_scan: Annotated[
        int | None,
        typer.Option(
            help="Laser shots per scan (SICK: 181 per line; multi-beam: beams per column, columns = shots / beams). "
            "Default: the sensor's own (SICK 20000, VLP-16 28800, HDL-32E 69504, HDL-64E 133312, OS1-64 65536)."
        ),
    ] = None,
    odometry: Annotated[
        bool,
        typer.Option(
            help="Write the drifting odometry (.pose files, odometry_kitti.txt); without it scans have no pose."
        ),
    ] = True,
    pattern: Annotated[
        str | None, typer.Option(hidden=True, help="Former name of --sensor: rotating or tilting.")
    ] = None,
    decimals: Annotated[int, typer.Option(help="Decimals of the centimetre coordinates in the files.")] = 2,
    overwrite: Annotated[bool, typer.Option(help="Replace scans already in OUT.")] = False,
) -> None:
    """Write a simulated session (uos) with ground truth and, unless --no-odometry, drifting odometry.

    Sensors, worlds, motions and timings in detail: docs/simulator.md.
    """
    from slam6d.metrics import absolute_trajectory_error
    from slam6d.simulate import SimulationConfig, simulate_session, validate

    if pattern is not None and sensor is not None:
        raise typer.BadParameter("give --sensor or its former name --pattern, not both")
    config = SimulationConfig(
        seed=seed,
        scans=scans,
        points_per_scan=points_per_scan,
        sensor=sensor if pattern is None else pattern,
        world=world,
        motion=motion,
        odometry=odometry,
        decimals=decimals,
    )
    try:
        validate(config)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    with progress_bar("simulating") as update:
        session = simulate_session(out, config, progress=update, overwrite=overwrite)
    typer.echo(f"{len(session.scan_paths)} scans, {sum(session.point_counts)} points written to {session.directory}")
    if session.odometry_file is None:
        typer.echo(f"ground truth: {session.ground_truth_file.name} (KITTI, cm); no odometry written")
        return
    drift = absolute_trajectory_error(session.odometry, session.ground_truth)
    typer.echo(f"ground truth: {session.ground_truth_file.name}, odometry: {session.odometry_file.name} (KITTI, cm)")
    typer.echo(f"odometry drift vs ground truth: ATE rmse {drift.rmse:.3f} m, max {drift.max:.3f} m")


@app.command(name="eval")
def evaluate(
    estimate: Annotated[Path, typer.Argument(help="Estimated poses, KITTI 3x4 lines (e.g. from `slam6d run`).")],
    reference: Annotated[Path, typer.Argument(help="Reference poses, KITTI 3x4 lines, same scans and units.")],
    align: Annotated[bool, typer.Option(help="Rigidly align the estimate to the reference before ATE.")] = True,
    delta: Annotated[int, typer.Option(help="RPE between scans this many steps apart.")] = 1,
    units_per_metre: Annotated[
        float | None, typer.Option(help="File units per metre (100 for uos cm) to also show metres.")
    ] = None,
    json_output: Annotated[bool, typer.Option("--json", help="Print the full result as JSON.")] = False,
) -> None:
    """Absolute (ATE) and relative (RPE) trajectory error of ESTIMATE against REFERENCE."""
    from slam6d.metrics import evaluate_pose_files
    from slam6d.trace import to_jsonable

    if delta < 1:
        raise typer.BadParameter("--delta must be at least 1")
    if units_per_metre is not None and units_per_metre <= 0:
        raise typer.BadParameter("--units-per-metre must be positive")
    result = evaluate_pose_files(estimate, reference, align=align, delta=delta)
    if json_output:
        typer.echo(json.dumps(to_jsonable(result), indent=1))
        return

    def length(value: float) -> str:
        metres = f" ({value / units_per_metre:.4f} m)" if units_per_metre else ""
        return f"{value:.4f}{metres}"

    ate, rpe = result.ate, result.rpe
    typer.echo(
        f"{ate.count} poses; lengths in the files' units"
        + (f", {units_per_metre:g} per metre" if units_per_metre else "")
    )
    typer.echo(f"ATE ({'rigidly aligned' if ate.aligned else 'not aligned'}):")
    for name in ("rmse", "mean", "median", "max"):
        typer.echo(f"  {name:7s} {length(getattr(ate, name))}")
    typer.echo(f"RPE (delta {rpe.delta}, {rpe.count} pairs):")
    typer.echo(f"  translation rmse {length(rpe.translation_rmse)}, max {length(rpe.translation_max)}")
    typer.echo(f"  rotation    rmse {rpe.rotation_rmse_deg:.4f} deg, max {rpe.rotation_max_deg:.4f} deg")


@app.command()
def run(
    source: Annotated[Path, typer.Argument(help="Directory of scans (or one file) to register.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Directory for poses_kitti.txt, .frames and report.json.")],
    fmt: FormatOption = None,
    poses: Annotated[
        Path | None, typer.Option(help="KITTI 3x4 odometry file (input frame) for formats without poses.")
    ] = None,
    first: Annotated[int, typer.Option(help="First scan index to use.")] = 0,
    last: Annotated[int | None, typer.Option(help="Last scan index to use (inclusive).")] = None,
    order: Annotated[
        str,
        typer.Option(
            help="Order of a folder's scan files: natural (2.pcd before 10.pcd, timestamps as numbers), name "
            "(plain text) or mtime (file time)."
        ),
    ] = "natural",
    min_range: Annotated[float | None, typer.Option(help="Drop points nearer than this (input units).")] = None,
    max_range: Annotated[float | None, typer.Option(help="Drop points farther than this (input units).")] = None,
    voxel: Annotated[float, typer.Option(help="Reduction voxel in metres (one real point per voxel); 0 = off.")] = 0.1,
    matching: Annotated[str, typer.Option(help="metascan (against recent registered scans) or pairwise.")] = "metascan",
    metascan_scans: Annotated[
        int, typer.Option(help="Registered scans the metascan holds (each searched with its own kd-tree).")
    ] = 1,
    method: Annotated[
        str, typer.Option(help="ICP error metric: point_to_plane or point_to_point (the paper's SVD).")
    ] = "point_to_plane",
    max_distance: Annotated[float, typer.Option(help="ICP max point-pair distance, metres.")] = 0.25,
    guess: Annotated[str, typer.Option(help="Octree initial guess: auto, always or never.")] = "auto",
    feature_guess: Annotated[
        bool, typer.Option(help="Try the FPFH+RANSAC feature guess when ICP still fits poorly after the octree search.")
    ] = True,
    loops: Annotated[bool, typer.Option(help="Detect loops.")] = True,
    loop_closing: Annotated[bool, typer.Option(help="Close detected loops by error diffusion.")] = True,
    relaxation: Annotated[str, typer.Option(help="Global relaxation: lum, graph, simultaneous or none.")] = "lum",
    memory_budget: Annotated[
        str | None,
        typer.Option(
            help="Keep the scans on disk (OUT/scan_store, float32) and at most this much of them in memory"
            " (e.g. 2GB); the stages keep only the reduced copies."
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Run the per-scan work (reduction, LUM's blocks) on a Dask cluster: local:N starts N worker"
            " processes here, tcp://HOST:PORT joins a running scheduler."
        ),
    ] = None,
    tilt_noise_deg: Annotated[
        float | None,
        typer.Option(
            help="The odometry's roll and pitch are an inclinometer's readings with this noise (degrees): a prior"
            " on every scan's tilt in registration and LUM. Default: what the session declares (a simulated"
            " session's simulation.json), else none; 0 = ignore a declared one."
        ),
    ] = None,
    residual_gate: Annotated[
        float,
        typer.Option(
            help="Sequential ICP leaves out pairs more than this many robust standard deviations off their"
            " plane once it has converged with all of them (0 = keep every pair; 4 removes the pull of short"
            " steps towards zero motion, docs/scale.md)."
        ),
    ] = 0.0,
    robust_scale: Annotated[
        float,
        typer.Option(
            help="Sequential ICP, once converged with all pairs, settles again with Geman-McClure weights of this"
            " scale in metres (0 = least squares; 0.05 removes the pull of short steps towards zero motion and"
            " keeps more elsewhere than --residual-gate, docs/scale.md)."
        ),
    ] = 0.0,
) -> None:
    """Register a whole sequence: sequential ICP, loop closing, global relaxation; write the trajectory."""
    import time
    from concurrent.futures import ThreadPoolExecutor

    from slam6d.io.order import SCAN_ORDERS
    from slam6d.io.registry import ReadOptions, read_sequence, resolve_format
    from slam6d.numba_blas import load_blas_bindings

    if order not in SCAN_ORDERS:
        raise typer.BadParameter(f"--order must be one of {', '.join(SCAN_ORDERS)}, got {order!r}")

    if tilt_noise_deg is not None and not (tilt_noise_deg >= 0 and math.isfinite(tilt_noise_deg)):
        raise typer.BadParameter(
            f"must be a number of degrees >= 0, got {tilt_noise_deg}", param_hint="--tilt-noise-deg"
        )
    declared_tilt = tilt_noise_deg is None
    if tilt_noise_deg is None:
        from slam6d.attitude import declared_tilt_noise

        tilt_noise_deg = declared_tilt_noise(source) if source.exists() else None
    tilt = tilt_noise_deg or None  # 0: the user says the readings are none

    def make_config() -> Any:
        from slam6d.engine_settings import pipeline_config

        # the flags by their [engine] names: parsed as session.toml's settings are
        return pipeline_config(
            {
                "voxel_size": voxel,
                "matching": matching,
                "metascan_scans": metascan_scans,
                "icp": {"max_distance": max_distance, "method": method},
                "octree_guess": guess,
                "feature_guess": feature_guess,
                "loops": loops,
                "loop_closing": loop_closing,
                "relaxation": relaxation,
                "tilt_noise_deg": tilt,
                "residual_gate": residual_gate,
                "robust_scale": robust_scale,
            }
        )

    if scheduler is not None:
        from slam6d.scheduler import SchedulerError, local_workers

        try:
            local_workers(scheduler)
        except SchedulerError as exc:
            raise typer.BadParameter(str(exc), param_hint="--scheduler") from None
    budget = None
    if memory_budget is not None:
        from slam6d.scan_store import parse_bytes

        try:
            budget = parse_bytes(memory_budget)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--memory-budget") from None
    load_blas_bindings()  # before numba's first call: 0.15 s of scipy.linalg it never uses
    began = time.perf_counter()
    store = None
    if source.exists():
        resolve_format(source, fmt)  # loads the format modules here, so the thread below never waits on one
    # The engine's modules load and the options are checked on a thread while the scans are read, which is
    # mostly compiled parsing without the GIL. Bad options stop the reading at the next scan.
    with ThreadPoolExecutor(1) as pool:
        configured = pool.submit(make_config)

        try:
            with progress_bar("reading scans") as update:

                def read_progress(done: int, total: int) -> None:
                    update(done, total)
                    if configured.done() and configured.exception() is not None:
                        raise _BadOptions

                if budget is None:
                    sequence = read_sequence(
                        source,
                        fmt,
                        ReadOptions(min_range, max_range),
                        first,
                        last,
                        poses,
                        progress=read_progress,
                        order=order,
                    )
                else:
                    from slam6d.scan_store import store_source

                    options = ReadOptions(min_range, max_range)
                    sequence, store = store_source(
                        out / "scan_store", source, fmt, options, budget, first, last, poses, read_progress, order
                    )
        except _BadOptions:
            pass
        read_seconds = time.perf_counter() - began
        try:
            config = configured.result()
        except (ValueError, Slam6dError) as exc:
            raise typer.BadParameter(str(exc)) from None
    from slam6d.pipeline import Pipeline, write_results
    from slam6d.posegraph import describe_components
    from slam6d.scheduler import open_scheduler

    workers = open_scheduler(scheduler)
    pipeline = Pipeline(sequence, config, store=store, scheduler=None if scheduler is None else workers)
    extra: dict[str, Any] = {"read_seconds": read_seconds}
    try:
        with progress_bar("registering") as update:
            report = pipeline.run(progress=lambda _stage, done, total: update(done, total))
    except Slam6dError as exc:
        if pipeline.report is None or pipeline.report.failure is None:
            raise
        # the stages before the failed one are kept: their poses and a report saying what failed
        paths = write_results(pipeline, out, extra | {"wall_seconds": time.perf_counter() - began})
        failure = pipeline.report.failure
        err.print(f"[red]error:[/red] the {failure.stage} stage failed: {exc}")
        if pipeline.report.components:
            err.print(
                f"each connected component was relaxed on its own: {describe_components(pipeline.report.components)}"
            )
        err.print(
            f"wrote the poses it has ({pipeline.report.registered_scans} of {len(sequence)} scans registered) to "
            f"{paths['poses']} and the failure to {paths['report']}"
        )
        raise typer.Exit(STAGE_FAILED) from None
    finally:
        workers.close()
    extra["wall_seconds"] = time.perf_counter() - began
    if store is not None:
        extra["scan_store"] = {"budget_bytes": store.budget, "peak_bytes": store.peak_bytes, "loads": store.loads}
    paths = write_results(pipeline, out, extra)
    closed = ", ".join(f"{i}-{j}" for i, j in report.loops_closed) or "none"
    typer.echo(f"{len(sequence)} scans registered; loops closed: {closed}")
    from slam6d.icp import WEAK_CONSTRAINT

    for summary in report.scan_summaries:  # a good fitness, yet one direction rests on a handful of points
        if summary.weakest_constraint < WEAK_CONSTRAINT:
            typer.echo(
                f"scan {summary.index} ({summary.name}): its fit barely fixes its translation along"
                f" {_axis_words(summary.weakest_direction)} ({100 * summary.weakest_constraint:.2f} % of the pairs'"
                f" worth){'; held where the motion puts it, not fitted' if summary.held_translations else ''};"
                " check it (report.json)"
            )
    if report.residual_before is not None and report.residual_after is not None:
        typer.echo(
            f"relaxation ({report.relaxation}): point-to-plane RMS {100 * report.residual_before:.2f} -> "
            f"{100 * report.residual_after:.2f} cm over {report.neighbour_pairs} neighbour pairs"
        )
    if pipeline.tilt is not None:
        typer.echo(
            f"tilt held to the odometry's inclinometer ({config.tilt_noise_deg:g}° noise"
            f"{', as the input declares' if declared_tilt else ''}); --tilt-noise-deg 0 turns it off"
        )
    stages = ", ".join(f"{k} {v:.2f}s" for k, v in report.stage_seconds.items())
    typer.echo(f"times: reading {read_seconds:.2f}s, {stages}; total {time.perf_counter() - began:.2f}s")
    typer.echo(f"peak memory {report.peak_memory_bytes / 1e9:.2f} GB")
    typer.echo(f"wrote {paths['poses']}, {paths['report']} and {len(sequence)} .frames files")


def _axis_words(direction: list[float]) -> str:
    """A scanner-frame direction by the axis it mostly lies along (the scanner's z: its height)."""
    axis = int(max(range(3), key=lambda k: abs(direction[k])))
    return ("the scanner's x", "the scanner's y", "the scanner's z (its height)")[axis]


STAGE_FAILED = 3  # exit code of `slam6d run` when a stage failed after earlier ones wrote their results


@app.command()
def relax(
    session_dir: Annotated[Path, typer.Argument(help="Session folder (with session.toml).")],
    method: Annotated[str, typer.Option(help="lum, graph (over the session's graph) or simultaneous.")] = "lum",
    fixed: Annotated[list[int] | None, typer.Option(help="Scans held in place (repeat the option); default 0.")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write the relaxed poses as KITTI lines.")] = None,
    commit: Annotated[bool, typer.Option(help="Store the relaxed poses as a new revision of the session.")] = False,
    author: Annotated[str, typer.Option(help="Who the journal names for --commit.")] = "slam6d relax",
    tilt_noise_deg: Annotated[
        float | None,
        typer.Option(
            help="The odometry's roll and pitch (revision 0) are an inclinometer's readings with this noise"
            " (degrees): a prior on every scan's tilt in lum and graph, as in slam6d run's relaxation. Default:"
            " the session's [engine] tilt_noise_deg (written for a folder that declares one), else none; 0 = off."
        ),
    ] = None,
) -> None:
    """Relax a session's current revision with its [engine] settings: the workbench's Relax, from the shell."""
    from slam6d.engine_settings import pipeline_config
    from slam6d.io.poses import write_kitti_poses
    from slam6d.numba_blas import load_blas_bindings
    from slam6d.relaxation_methods import reduced_models
    from slam6d.residuals import displacements
    from slam6d.session import Session
    from slam6d.session_relaxation import relax_revision, revision_tilt_prior, session_readings

    if tilt_noise_deg is not None and not (tilt_noise_deg >= 0 and math.isfinite(tilt_noise_deg)):
        raise typer.BadParameter(
            f"must be a number of degrees >= 0, got {tilt_noise_deg}", param_hint="--tilt-noise-deg"
        )
    if tilt_noise_deg and method == "simultaneous":
        raise typer.BadParameter(
            "relaxation 'simultaneous' has no tilt prior; the inclinometer's readings need lum or graph",
            param_hint="--tilt-noise-deg",
        )
    load_blas_bindings()  # before numba's first call: 0.15 s of scipy.linalg it never uses
    session = Session.open(session_dir)
    stated = {} if tilt_noise_deg is None else {"tilt_noise_deg": tilt_noise_deg or None}  # 0: no readings
    config = pipeline_config(session.config.engine, stated)
    with progress_bar("reading scans") as update:
        sequence = session.load_sequence(update)
    revision = session.get_revision()
    models = reduced_models([s.points for s in sequence.scans], config.voxel_size, config.icp)
    tilt = revision_tilt_prior(
        config, method, lambda: session_readings(session, [s.has_pose for s in sequence.scans]), models
    )
    held = fixed or [0]
    with progress_bar(f"relaxing ({method})") as update:
        result = relax_revision(
            method,
            models,
            revision,
            held,
            config,
            tilt,
            progress=lambda done, _residual, _moved: update(done, config.relax.max_rounds),
        )
    typer.echo(
        f"{method}: {result.iterations} round(s), point-to-plane RMS {100 * result.residual_before:.2f} -> "
        f"{100 * result.residual_after:.2f} cm; largest move {max(displacements(revision.poses, result.poses)):.3f} m"
    )
    if tilt is not None:
        typer.echo(
            f"tilt held to the odometry's inclinometer ({tilt.noise_deg:g}° noise"
            f"{', as the session declares' if tilt_noise_deg is None else ''}); --tilt-noise-deg 0 turns it off"
        )
    if out is not None:
        write_kitti_poses(out, result.poses)
        typer.echo(f"wrote {out} (canonical frame)")
    if commit:
        parameters = {
            "method": method,
            "fixed": held,
            "rounds": result.iterations,
            "tilt_noise_deg": None if tilt is None else tilt.noise_deg,
        }
        # onto the head as it is now: a workbench editing this session meanwhile keeps its other edits
        number = session.journal.commit(result.poses, author, f"relax_{method}", parameters, base=revision.number)
        typer.echo(f"stored as revision {number}")


bundle_app = typer.Typer(no_args_is_help=True, help="Hand a whole session (its history) over as one zip.")
app.add_typer(bundle_app, name="bundle")


@bundle_app.command("export")
def bundle_export(
    session: Annotated[Path, typer.Argument(help="Session folder (holding session.toml).")],
    out: Annotated[Path, typer.Argument(help="The zip to write.")],
    scans: Annotated[bool, typer.Option("--scans", help="Include the scan files themselves.")] = False,
    data_root: Annotated[
        Path | None,
        typer.Option(help="Without --scans: also record the scans' place inside this folder (a server's data root)."),
    ] = None,
) -> None:
    """Write SESSION's bundle: manifest (sha256 per file), session.toml, journal, traces, camera path; the
    scans themselves with --scans, otherwise where they are and each scan file's sha256."""
    from slam6d.bundle import export_bundle

    summary = export_bundle(session, out, include_scans=scans, data_root=data_root)
    included = "with" if summary.scans_included else "without"
    typer.echo(f"{summary.path}: {summary.files} files, {summary.bytes:,} bytes, {included} scans")


@bundle_app.command("import")
def bundle_import(
    bundle: Annotated[Path, typer.Argument(help="A bundle written by `slam6d bundle export`.")],
    sessions_dir: Annotated[Path, typer.Argument(help="Folder of sessions to add the new session to.")],
    data_root: Annotated[
        Path | None,
        typer.Option(help="Where to look for the scans of a bundle exported without them (as a server's --data-root)."),
    ] = None,
) -> None:
    """Make a new session in SESSIONS_DIR with BUNDLE's history; a bundle that fails a check writes nothing.

    A bundle exported without its scans is re-linked to them - under --data-root at the place they had
    in the exporter's data root, or else where they were - once every scan file's sha256 matches."""
    from slam6d.bundle import import_bundle, local_source_finder

    finder = local_source_finder(data_root)
    session = import_bundle(bundle, sessions_dir, find_source=finder, author=os.environ.get("USER", ""))
    typer.echo(f"{session.folder}: session '{session.name}' at revision {session.journal.head}")


class _BadOptions(Exception):  # noqa: N818 - a signal, not an error shown to anyone
    """Stops reading scans once the options turned out invalid."""


def main() -> None:
    """Console entry point: engine errors become one clear line and exit code 2, not a traceback."""
    # numba's OpenMP threads then sleep between parallel kernels instead of spinning: on a shared machine a
    # spinning thread holds the core its partner needs (render 1280x720/2M: 28 -> 73 fps at load 2)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        app()
    except Slam6dError as exc:
        err.print(f"[red]error:[/red] {exc}")
        _leave(2)
    except SystemExit as done:  # how typer ends every command
        _leave(done.code)


def _leave(code: object) -> NoReturn:
    """Exit without tearing the interpreter down. With numba, LLVM, scipy and OpenMP loaded the
    teardown took 0.5-1 s after `slam6d run` had finished (a tenth of the whole command); every file
    a command writes is closed by then, so only the standard streams still need flushing."""
    if isinstance(code, str):
        print(code, file=sys.stderr)  # sys.exit("message") prints it and exits with 1
    for stream in (sys.stdout, sys.stderr):
        with suppress(OSError, ValueError):  # a closed pipe or stream: nothing left to say there
            stream.flush()
    os._exit(code if isinstance(code, int) else 0 if code is None else 1)


if __name__ == "__main__":
    main()
