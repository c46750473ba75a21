"""How far `slam6d run`'s map moves when its input moves by less than any scanner can measure.

A registration whose result depends on the last tenth of a millimetre of its input is a lottery on
real scans: each of its decisions (which start's fit to keep, whether to search, which translations
to hold) is a threshold somewhere, and a fit that lands next to one flips with the input's rounding.
This benchmark measures that. Each session is simulated once (``slam6d simulate``, no odometry,
deterministic by seed) and written again ``--variants`` times with every coordinate moved by up to
0.06 mm and rounded to the files' 0.1 mm (what reading and writing the same scans through another
tool does to them); `slam6d run` (a new process, as a user starts it) registers the original and
every variant, and per session the ATE of each against the simulator's ground truth (cm, rigidly
aligned), their mean, worst and spread (worst - best) are printed, then the sum of the spreads and
the worst ATE over all sessions.

Sessions: the robustness matrix's twelve 10-scan sessions without odometry (VLP-16, HDL-32E,
OS1-64 x indoor hand-held walk, outdoor car x seeds 1-2), six 30-scan hand-held walks indoors
(turns up to 45° between scans) and three 30-scan drives.

    .venv/bin/python benchmarks/stability.py [--variants 4] [--only walk30] [--work /tmp/stability]
        [--sensors vlp16,hdl32,os1-64] [--seeds 1,2] [--against ../before]

``--against`` runs another checkout's `slam6d run` on the same files, session by session.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.child_process import run_slam6d  # noqa: E402
from slam6d.geometry import UOS  # noqa: E402
from slam6d.io.poses import read_kitti_poses  # noqa: E402
from slam6d.io.uos import discover_uos, read_uos_scan, write_uos_scan  # noqa: E402
from slam6d.metrics import absolute_trajectory_error  # noqa: E402
from slam6d.simulate import SimulationConfig, simulate_session  # noqa: E402

JITTER_CM = 0.006  # up to 0.06 mm, then rounded to the files' 0.01 cm: each coordinate moves by 0 or 0.1 mm


def sessions(sensors: list[str], seeds: list[int]) -> dict[str, SimulationConfig]:
    """The 10-scan walks and drives and the 30-scan walks of each of ``sensors`` and ``seeds``, and
    three 30-scan drives (VLP-16 seed 1, HDL-32E seed 2, OS1-64 seed 2)."""
    found: dict[str, SimulationConfig] = {}
    for world in ("indoor", "outdoor"):
        for sensor in sensors:
            for seed in seeds:
                found[f"{world}10/{sensor}/seed{seed}"] = SimulationConfig(
                    seed=seed, scans=10, sensor=sensor, world=world, odometry=False
                )
    for sensor in sensors:
        for seed in seeds:
            found[f"walk30/{sensor}/seed{seed}"] = SimulationConfig(
                seed=seed, scans=30, sensor=sensor, world="indoor", motion="handheld", odometry=False
            )
    for sensor, seed in (("vlp16", 1), ("hdl32", 2), ("os1-64", 2)):
        found[f"car30/{sensor}/seed{seed}"] = SimulationConfig(
            seed=seed, scans=30, sensor=sensor, world="outdoor", motion="car", odometry=False
        )
    return found


def rerounded(original: Path, variant: Path, seed: int) -> None:
    """``original``'s session written to ``variant`` with every coordinate moved by up to
    ``JITTER_CM`` and rounded to 0.01 cm as the simulator writes it; other files copied."""
    variant.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    scans = set(discover_uos(original))
    for path in sorted(original.iterdir()):
        if path in scans:
            points = read_uos_scan(path).points
            moved = points + rng.uniform(-JITTER_CM, JITTER_CM, points.shape)
            write_uos_scan(variant, int(path.stem[4:]), moved, None, decimals=2)
        elif path.is_file():
            shutil.copy(path, variant / path.name)


def ate_cm(tree: Path, folder: Path, truth: list[np.ndarray]) -> float:
    """`slam6d run` of the checkout ``tree`` on ``folder``: its ATE (cm)."""
    poses = [UOS.pose_to_canonical(p) for p in run_slam6d(folder, tree=tree).poses]
    return 100.0 * absolute_trajectory_error(poses, truth).rmse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", type=int, default=4, help="re-rounded copies of each session (besides it)")
    parser.add_argument("--only", default="", help="the sessions whose name contains this")
    parser.add_argument("--sensors", default="vlp16,hdl32,os1-64", help="of the 10-scan and 30-scan walks")
    parser.add_argument("--seeds", default="1,2", help="of the 10-scan and 30-scan walks")
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "slam6d_stability")
    parser.add_argument("--against", type=Path, help="another checkout whose slam6d run is measured too")
    args = parser.parse_args()
    trees = [ROOT] + ([args.against.resolve()] if args.against else [])
    spreads: dict[Path, list[float]] = {tree: [] for tree in trees}
    worst: dict[Path, float] = dict.fromkeys(trees, 0.0)
    print(f"ATE (cm) of slam6d run on each session and {args.variants} re-rounded copies (0.1 mm)")
    seeds = [int(seed) for seed in args.seeds.split(",")]
    for name, config in sessions(args.sensors.split(","), seeds).items():
        if args.only not in name:
            continue
        folder = args.work / name.replace("/", "_")
        if not (folder / "ground_truth_kitti.txt").exists():
            simulate_session(folder, config, overwrite=True)
        truth = [UOS.pose_to_canonical(p) for p in read_kitti_poses(folder / "ground_truth_kitti.txt")]
        variants = [folder]
        for k in range(1, args.variants + 1):
            variant = args.work / f"{folder.name}_rerounded{k}"
            if not (variant / "ground_truth_kitti.txt").exists():
                rerounded(folder, variant, k)
            variants.append(variant)
        for tree in trees:
            errors = [ate_cm(tree, variant, truth) for variant in variants]
            spread = max(errors) - min(errors)
            spreads[tree].append(spread)
            worst[tree] = max(worst[tree], max(errors))
            label = "" if len(trees) == 1 else f" [{tree.name}]"
            print(
                f"{name + label:32s} "
                + " ".join(f"{e:6.2f}" for e in errors)
                + f" | mean {statistics.mean(errors):5.2f} worst {max(errors):6.2f} spread {spread:6.2f}",
                flush=True,
            )
    for tree in trees:
        label = "" if len(trees) == 1 else f"{tree}: "
        print(f"{label}sum of spreads {sum(spreads[tree]):.2f} cm, worst ATE {worst[tree]:.2f} cm")


if __name__ == "__main__":
    main()
