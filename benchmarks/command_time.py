"""`slam6d run` without odometry beside a small_gicp GICP chain, both as a user starts them.

The issue's target is a session without odometry "within 3x the wall time of a small_gicp GICP
chain on the same files". ``benchmarks/robustness.py`` times the chain inside its own process, where
small_gicp is imported already; here the chain is also timed as a command of its own (a fresh Python
process importing numpy and small_gicp, plus the reading and the chain from identity increments timed
in this process), so both pay their start-up. Per session it prints, median over
``--repeats`` interleaved runs: wall and CPU (user + system) of ``slam6d run``, of the chain as a
command and of the chain in this process, each ratio, the ATE of both (cm, against the simulator's
ground truth), and the run's stage times from its ``report.json``. Wall time is CPU time plus
waiting for a core on a loaded machine; CPU is the figure that survives the load (both sides' OpenMP
threads sleep while they wait, ``OMP_WAIT_POLICY=PASSIVE`` as ``slam6d`` sets it, so a spinning
thread's wait is not counted as work).

Sessions (simulated here, deterministic by seed, no odometry):

* ``vlp16-10``: 10 scans of a VLP-16 on a car in the outdoor streets (the matrix's 10-scan size);
* ``indoor-30``: a 30-scan hand-held VLP-16 walk through the indoor world (turns up to 45°);
* ``os1-21``: the issue's own real example simulated: 21 OS1-64 keyframes from a car in the
  outdoor streets, 1,536 columns so each scan holds ~65k points as the real ones did.

    .venv/bin/python benchmarks/command_time.py [--sessions vlp16-10,indoor-30,os1-21] [--repeats 3]
        [--against ../before]

``--against`` times another checkout's ``slam6d run`` in alternation with this one's (before/after at
the same load); its kernels are compiled by a first run of each that is not counted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

# set before small_gicp's OpenMP starts: its waiting threads then sleep, as `slam6d run`'s do (slam6d.cli.main),
# instead of spinning on a loaded machine and counting the spin as the chain's CPU
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.child_process import CHAIN_STARTUP, add_against_option, checkouts, timed_command  # noqa: E402
from benchmarks.trajectory import load, small_gicp_chained  # noqa: E402
from slam6d.geometry import UOS, Matrix  # noqa: E402
from slam6d.io.poses import read_kitti_poses  # noqa: E402
from slam6d.io.registry import read_sequence  # noqa: E402
from slam6d.metrics import absolute_trajectory_error  # noqa: E402
from slam6d.simulate import SimulationConfig, simulate_session  # noqa: E402

SESSIONS = {
    "vlp16-10": SimulationConfig(seed=1, scans=10, sensor="vlp16", world="outdoor", motion="car", odometry=False),
    "indoor-30": SimulationConfig(seed=1, scans=30, sensor="vlp16", world="indoor", motion="handheld", odometry=False),
    "os1-21": SimulationConfig(
        seed=1, scans=21, sensor="os1-64", world="outdoor", motion="car", odometry=False, points_per_scan=64 * 1536
    ),
}


def ate_cm(poses: list[Matrix], truth: list[Matrix]) -> float:
    return 100 * absolute_trajectory_error(poses, truth).rmse


def median_pair(times: list[tuple[float, float]]) -> tuple[float, float]:
    return statistics.median(t[0] for t in times), statistics.median(t[1] for t in times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", default=",".join(SESSIONS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--keep", type=Path, help="simulate into (and reuse) this folder instead of a temporary one")
    add_against_option(parser, "`slam6d run`")
    args = parser.parse_args()
    trees = checkouts(args.against)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        print(f"{load()}; median of {args.repeats}, CPU = user + system")
        for name in args.sessions.split(","):
            folder = root / name
            if not (folder / "ground_truth_kitti.txt").exists():
                simulate_session(folder, SESSIONS[name], overwrite=True)
            truth = [UOS.pose_to_canonical(p) for p in read_kitti_poses(folder / "ground_truth_kitti.txt")]
            outs = [Path(tmp) / f"{name}-out-{t}" for t in range(len(trees))]
            run = [sys.executable, "-m", "slam6d.cli", "run", str(folder), "--format", "uos", "--out"]
            for tree, out in zip(trees, outs, strict=True):
                timed_command([*run, str(out)], tree)  # compiles any kernel not cached yet
            run_times: list[list[tuple[float, float]]] = [[] for _ in trees]
            stages: list[list[dict[str, float]]] = [[] for _ in trees]
            chain_times, inproc_times = [], []
            for _ in range(args.repeats):
                for t, (tree, out) in enumerate(zip(trees, outs, strict=True)):
                    run_times[t].append(timed_command([*run, str(out)], tree))
                    report = json.loads((out / "report.json").read_text())
                    stages[t].append({"reading": report["read_seconds"], **report["stage_seconds"]})
                startup_wall, startup_cpu = timed_command([sys.executable, "-c", CHAIN_STARTUP])
                wall, cpu = time.perf_counter(), time.process_time()
                chained = small_gicp_chained([s.points for s in read_sequence(folder, "uos")], [np.eye(4)] * len(truth))
                inproc_times.append((time.perf_counter() - wall, time.process_time() - cpu))
                chain_times.append((startup_wall + inproc_times[-1][0], startup_cpu + inproc_times[-1][1]))
            (chain_wall, chain_cpu), (in_wall, in_cpu) = median_pair(chain_times), median_pair(inproc_times)
            points = sum(len(s.points) for s in read_sequence(folder, "uos")) // len(truth)
            print(f"\n{name}: {len(truth)} scans, {points} points each")
            print(
                f"  chain as command  wall {chain_wall:6.2f} s  CPU {chain_cpu:6.2f} s  ATE {ate_cm(chained, truth):6.2f} cm"
            )
            print(f"  chain in process  wall {in_wall:6.2f} s  CPU {in_cpu:6.2f} s")
            for t, tree in enumerate(trees):
                run_wall, run_cpu = median_pair(run_times[t])
                poses = [UOS.pose_to_canonical(p) for p in read_kitti_poses(outs[t] / "poses_kitti.txt")]
                label = "slam6d run" if len(trees) == 1 else f"run ({tree.name})"
                print(f"  {label:17s} wall {run_wall:6.2f} s  CPU {run_cpu:6.2f} s  ATE {ate_cm(poses, truth):6.2f} cm")
                print(
                    f"    run / chain: as commands x{run_wall / chain_wall:.1f} wall, x{run_cpu / chain_cpu:.1f} CPU;"
                    f" against the chain in process x{run_wall / in_wall:.1f} wall, x{run_cpu / in_cpu:.1f} CPU"
                )
                stage = {k: statistics.median(s.get(k, 0.0) for s in stages[t]) for k in stages[t][0]}
                print("    stages (wall): " + ", ".join(f"{k} {v:.2f} s" for k, v in stage.items()))
        print(f"\n{load()}")


if __name__ == "__main__":
    main()
