"""How `slam6d run` grows with the session: wall, stage times, neighbour pairs, peak memory and ATE.

Cases (each simulated once into ``--work`` by ``slam6d simulate`` and reused afterwards):

* the dense loop: the seed's ~98 m loop (``--seed 3 --points-per-scan 30000``) scanned 100, 200
  and 400 times, so the same place is seen by ever more scans (the case where an unbounded
  neighbour graph grows with the square of the density);
* the campus (``--world campus``, 20k shots per scan): a km-scale drive scanned 250, 500 and
  1,000 times, where the path grows with the scans.

Every run is the command line a user starts (start-up, reading the files, writing the results),
its figures read from the ``report.json`` it writes (``wall_seconds``, ``stage_seconds``,
``neighbour_pairs``, ``peak_memory_bytes``) and its ATE against the simulator's ground truth,
after the run and before its relaxation (each scan's last pose before relaxation, from the
``.frames`` history the run writes: what registration and loop closing alone reached). The
growth exponent is the slope of log(time) over log(scans) per case (1 = linear), for wall and for
CPU time (user + system of the run and its workers, which the machine's other work inflates far
less than wall time). With
``--scheduler local:2`` each run is repeated on a local Dask cluster and the largest distance
between its scan positions and the serial run's is printed. Timings on a shared machine swing
with its load: the load average is printed beside every run.

With ``--profile-relaxation`` each campus session is instead registered in this process (loops
closed, no relaxation), and ``slam6d run``'s LUM relaxation is then run on those poses under
``cProfile``: its time split into the rounds' closest-point queries and normal-equation blocks,
finding the bounded neighbour graph, gathering each scan's batch of neighbour points, and the
sparse linear algebra (working out the block pattern, factorising and solving) - the measurement
that decides whether the solve needs windows or a hierarchy (docs/scale.md).

Run: ``.venv/bin/python benchmarks/scale.py --work /tmp/scale --loop 100 200 400 --campus 250 500 1000``;
``.venv/bin/python benchmarks/scale.py --work /tmp/scale --loop --campus 250 500 --profile-relaxation``.
The figures measured so far, with their load, are in docs/scale.md; the campus runs (loops closed,
ATE and why it stays in metres) in docs/robustness.md, "Loops on the campus".
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.geometry import UOS
from slam6d.io.frames import FrameType, read_frames
from slam6d.io.poses import read_kitti_poses
from slam6d.metrics import absolute_trajectory_error

CASES = {
    "loop": ["--seed", "3", "--points-per-scan", "30000"],
    "campus": ["--world", "campus", "--seed", "3", "--points-per-scan", "20000"],
}


@dataclass
class Run:
    case: str
    scans: int
    wall: float
    cpu: float  # user + system seconds of the run (its worker processes included): barely inflated by load
    stages: dict[str, float]
    pairs: int
    peak_gb: float
    ate_cm: float
    unrelaxed_ate_cm: float  # before the relaxation stage: registration and loop closing alone
    load: float
    poses: np.ndarray  # scan positions, metres


def cli(*arguments: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "slam6d.cli", *arguments], capture_output=True, text=True, check=False)


def session(work: Path, case: str, scans: int) -> Path:
    directory = work / f"{case}{scans}"
    if not (directory / "ground_truth_kitti.txt").exists():
        done = cli("simulate", str(directory), "--scans", str(scans), "--overwrite", *CASES[case])
        if done.returncode != 0:
            raise SystemExit(f"slam6d simulate failed for {case} {scans}:\n{done.stderr}")
    return directory


def run(directory: Path, case: str, scans: int, extra: list[str]) -> Run:
    out = directory.parent / f"{directory.name}_out{'_' + '_'.join(extra).replace('/', '') if extra else ''}"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = cli("run", str(directory), "--format", "uos", "--out", str(out), *extra)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        raise SystemExit(f"slam6d run failed on {directory}:\n{done.stdout}\n{done.stderr}")
    report = json.loads((out / "report.json").read_text())
    truth = [UOS.pose_to_canonical(p) for p in read_kitti_poses(directory / "ground_truth_kitti.txt")]
    estimate = [UOS.pose_to_canonical(p) for p in read_kitti_poses(out / "poses_kitti.txt")]
    unrelaxed = [UOS.pose_to_canonical(unrelaxed_pose(out / f"{name}.frames")) for name in scan_names(report)]
    return Run(
        case,
        scans,
        float(report["wall_seconds"]),
        cpu,
        {k: float(v) for k, v in report["stage_seconds"].items() if v >= 0.01},
        int(report["neighbour_pairs"]),
        report["peak_memory_bytes"] / 1e9,
        100 * absolute_trajectory_error(estimate, truth).rmse,
        100 * absolute_trajectory_error(unrelaxed, truth).rmse,
        os.getloadavg()[0],
        np.array([p[:3, 3] for p in estimate]),
    )


def scan_names(report: dict[str, Any]) -> list[str]:
    """The scans' names in order, as the run named their ``.frames`` files."""
    return [summary["name"] for summary in report["scan_summaries"]]


def unrelaxed_pose(frames: Path) -> np.ndarray:
    """A scan's last pose before relaxation: the newest entry of its history not written by it."""
    entries = read_frames(frames)
    return next(pose for pose, kind in reversed(entries) if kind not in (FrameType.LUM, FrameType.ICP_INACTIVE))


RELAXATION_PARTS = {  # (module, function) whose cumulative time makes up each part of the split
    "rounds' queries and blocks": [("lum.py", "_scan_system"), ("lum.py", "_remote_scan_system")],
    "neighbour graph": [("relax.py", "neighbour_pairs")],
    "batches of neighbour points": [("lum.py", "_batches")],
    "block pattern": [("block_system.py", "__init__")],
    "factorise and solve": [("block_system.py", "solve")],
}


def profile_relaxation(directory: Path) -> None:
    """Register ``directory`` as ``slam6d run`` does up to its relaxation, then profile that relaxation."""
    import cProfile
    import pstats
    import time
    from dataclasses import replace

    from slam6d.io.registry import read_sequence
    from slam6d.pipeline import Pipeline, PipelineConfig
    from slam6d.relaxation_methods import relax_poses

    config = PipelineConfig()
    pipeline = Pipeline(read_sequence(directory, "uos"), replace(config, relaxation="none"))
    pipeline.run()
    if config.relax_registration_models:  # as the relaxation stage hands them over
        for k in range(len(pipeline.sequence)):
            model = pipeline.registration_model(k)
            if model is not pipeline.models.index(k):
                pipeline.models.share_plane_model(k, model)
    profile = cProfile.Profile()
    began = time.perf_counter()
    profile.enable()
    result = relax_poses("lum", pipeline.models, pipeline.poses, links=pipeline.links, config=config.relax)
    profile.disable()
    seconds = time.perf_counter() - began
    stats = pstats.Stats(profile).stats  # type: ignore[attr-defined]
    split = {  # part: (cumulative seconds, calls)
        part: np.sum(
            [
                (row[3], row[1])
                for (filename, _line, function), row in stats.items()
                if any(filename.endswith("slam6d/" + module) and function == name for module, name in functions)
            ]
            or [(0.0, 0)],
            axis=0,
        )
        for part, functions in RELAXATION_PARTS.items()
    }
    shares = ", ".join(
        f"{part} {t:.1f} s ({100 * t / seconds:.0f} %, {int(calls)} calls)" for part, (t, calls) in split.items()
    )
    print(
        f"| {directory.name} | {len(pipeline.poses)} | {seconds:.1f} s | {result.iterations} | {len(result.neighbours):,}"
        f" | {shares} | {os.getloadavg()[0]:.1f} |",
        flush=True,
    )


def exponent(scans: list[int], seconds: list[float]) -> float:
    """Slope of log(seconds) against log(scans): 1 is linear, 2 quadratic."""
    return float(np.polyfit(np.log(scans), np.log(seconds), 1)[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("/tmp/slam6d-scale"), help="sessions and results go here")
    parser.add_argument("--loop", type=int, nargs="*", default=[100, 200, 400], help="dense-loop scan counts")
    parser.add_argument("--campus", type=int, nargs="*", default=[250, 500, 1000], help="campus scan counts")
    parser.add_argument("--memory-budget", help="passed to slam6d run (e.g. 2GB)")
    parser.add_argument("--scheduler", help="also run on this Dask scheduler (e.g. local:2) and compare")
    parser.add_argument(
        "--profile-relaxation", action="store_true", help="profile LUM relaxation on the campus sessions instead"
    )
    args = parser.parse_args()
    if args.profile_relaxation:
        print(f"LUM relaxation under cProfile, {os.cpu_count()} cores (cProfile itself adds some time)")
        print("| session | scans | relaxation | rounds | neighbour pairs | of it | load |")
        print("|---|---|---|---|---|---|---|")
        for scans in args.campus:
            profile_relaxation(session(args.work, "campus", scans))
        return
    extra = ["--memory-budget", args.memory_budget] if args.memory_budget else []
    print(f"slam6d run, {os.cpu_count()} cores; load average before: {os.getloadavg()[0]:.1f}")
    print("| case | scans | wall | CPU | stages | neighbour pairs | peak memory | ATE | ATE before relaxation | load |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for case, counts in (("loop", args.loop), ("campus", args.campus)):
        runs = []
        for scans in counts:
            directory = session(args.work, case, scans)
            r = run(directory, case, scans, extra)
            runs.append(r)
            stages = ", ".join(f"{k} {v:.1f}" for k, v in r.stages.items())
            print(
                f"| {case} | {scans} | {r.wall:.1f} s | {r.cpu:.1f} s | {stages} | {r.pairs:,} | {r.peak_gb:.2f} GB"
                f" | {r.ate_cm:.2f} cm | {r.unrelaxed_ate_cm:.2f} cm | {r.load:.1f} |",
                flush=True,
            )
            if args.scheduler:
                d = run(directory, case, scans, [*extra, "--scheduler", args.scheduler])
                apart = float(np.linalg.norm(d.poses - r.poses, axis=1).max())
                print(
                    f"|   {args.scheduler} | {scans} | {d.wall:.1f} s | {d.cpu:.1f} s | | {d.pairs:,} | {d.peak_gb:.2f} GB"
                    f" | {d.ate_cm:.2f} cm (positions {100 * apart:.4f} cm from serial) | | {d.load:.1f} |",
                    flush=True,
                )
        if len(runs) >= 2:
            first, last = runs[0], runs[-1]
            scans = [r.scans for r in runs]
            print(
                f"{case}: wall grows as scans^{exponent(scans, [r.wall for r in runs]):.2f}, CPU as"
                f" scans^{exponent(scans, [r.cpu for r in runs]):.2f}; t({last.scans})/t({first.scans}) ="
                f" {last.wall / first.wall:.1f} wall, {last.cpu / first.cpu:.1f} CPU for"
                f" {last.scans / first.scans:.0f}x the scans"
            )


if __name__ == "__main__":
    main()
