"""How `slam6d run` grows with the session: wall, stage times, neighbour pairs, peak memory and ATE.

Cases (each simulated once into ``--work`` by ``slam6d simulate`` and reused afterwards):

* the dense loop: the seed's ~98 m loop (``--seed 3 --points-per-scan 30000``) scanned 100, 200
  and 400 times, so the same place is seen by ever more scans (the case where an unbounded
  neighbour graph grows with the square of the density);
* the campus (``--world campus``, 20k shots per scan): a km-scale drive scanned 250, 500 and
  1,000 times, where the path grows with the scans.

Every run is the command line a user starts (start-up, reading the files, writing the results),
its figures read from the ``report.json`` it writes (``wall_seconds``, ``stage_seconds``,
``neighbour_pairs``, ``peak_memory_bytes``) and its ATE against the simulator's ground truth. The
growth exponent is the slope of log(time) over log(scans) per case (1 = linear), for wall and for
CPU time (user + system of the run and its workers, which the machine's other work inflates far
less than wall time). With
``--scheduler local:2`` each run is repeated on a local Dask cluster and the largest distance
between its scan positions and the serial run's is printed. Timings on a shared machine swing
with its load: the load average is printed beside every run.

Run: ``.venv/bin/python benchmarks/scale.py --work /tmp/scale --loop 100 200 400 --campus 250 500 1000``.
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

import numpy as np

from slam6d.geometry import UOS
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
    return Run(
        case,
        scans,
        float(report["wall_seconds"]),
        cpu,
        {k: float(v) for k, v in report["stage_seconds"].items() if v >= 0.01},
        int(report["neighbour_pairs"]),
        report["peak_memory_bytes"] / 1e9,
        100 * absolute_trajectory_error(estimate, truth).rmse,
        os.getloadavg()[0],
        np.array([p[:3, 3] for p in estimate]),
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
    args = parser.parse_args()
    extra = ["--memory-budget", args.memory_budget] if args.memory_budget else []
    print(f"slam6d run, {os.cpu_count()} cores; load average before: {os.getloadavg()[0]:.1f}")
    print("| case | scans | wall | CPU | stages | neighbour pairs | peak memory | ATE | load |")
    print("|---|---|---|---|---|---|---|---|---|")
    for case, counts in (("loop", args.loop), ("campus", args.campus)):
        runs = []
        for scans in counts:
            directory = session(args.work, case, scans)
            r = run(directory, case, scans, extra)
            runs.append(r)
            stages = ", ".join(f"{k} {v:.1f}" for k, v in r.stages.items())
            print(
                f"| {case} | {scans} | {r.wall:.1f} s | {r.cpu:.1f} s | {stages} | {r.pairs:,} | {r.peak_gb:.2f} GB"
                f" | {r.ate_cm:.2f} cm | {r.load:.1f} |",
                flush=True,
            )
            if args.scheduler:
                d = run(directory, case, scans, [*extra, "--scheduler", args.scheduler])
                apart = float(np.linalg.norm(d.poses - r.poses, axis=1).max())
                print(
                    f"|   {args.scheduler} | {scans} | {d.wall:.1f} s | {d.cpu:.1f} s | | {d.pairs:,} | {d.peak_gb:.2f} GB"
                    f" | {d.ate_cm:.2f} cm (positions {100 * apart:.4f} cm from serial) | {d.load:.1f} |",
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
