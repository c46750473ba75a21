"""Octree initial guess: how often it rescues ICP from a poor start, how close it lands, what it costs.

For each real pair, the reference relative pose is disturbed by a random offset about the data's
centroid: a horizontal shift of 0.7–1.0 m (scaled to the object for the bunny: 5 % of its extent,
as 1 m is of a 20 m hall), yaw 20–30° either way, roll and pitch uniform in ±5°, z ±0.1 m. Then

* ``plain``: ICP from the disturbed start;
* ``guess``: :func:`slam6d.initial_guess.octree_guess` from the same start (error of the guess alone);
* ``guess+icp``: ICP from the guess.

A run "succeeds" when it ends within 2 cm / 0.5° of the reference (bunny: 1 mm / 0.5°). Pairs: BALM
hall consecutive scans (ICP defaults: point-to-plane, 0.25 m) and bunny neighbours (point-to-point,
3 mm, full resolution). "cpu s" is the CPU time of all threads of the guess (the machine may be
shared, so wall time is shown beside it).

    .venv/bin/python benchmarks/initial_guess.py              # 5 BALM pairs + 4 bunny pairs, 2 starts each
    .venv/bin/python benchmarks/initial_guess.py --starts 4 --seed 1
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from slam6d.errors import RegistrationError  # noqa: E402
from slam6d.geometry import invert, pose_difference, transform_points  # noqa: E402
from slam6d.icp import ICPConfig, icp  # noqa: E402
from slam6d.initial_guess import cloud_extent, octree_guess, offset_transform  # noqa: E402
from slam6d.io import read_sequence  # noqa: E402

DEG = math.pi / 180.0
BALM_PAIRS = [(5, 6), (25, 26), (45, 46), (65, 66), (85, 86)]
BUNNY_PAIRS = [("bun000", "bun045"), ("bun045", "bun090"), ("bun270", "bun315"), ("bun315", "bun000")]
BUNNY_ICP = ICPConfig(
    method="point_to_point",
    max_distance=0.003,
    max_iterations=100,
    data_voxel_size=0.0,
    epsilon=1e-6,
    stage_epsilon=1e-6,
)


def data_root() -> Path:
    return Path(os.environ.get("SLAM6D_DATA", ROOT.parent / "shared" / "data"))


def random_offsets(rng: np.random.Generator, shift: float) -> tuple[float, ...]:
    heading = rng.uniform(0.0, 2.0 * math.pi)
    length = rng.uniform(0.7, 1.0) * shift
    return (
        length * math.cos(heading),
        length * math.sin(heading),
        rng.uniform(-0.1, 0.1) * shift,
        rng.uniform(-5.0, 5.0) * DEG,
        rng.uniform(-5.0, 5.0) * DEG,
        rng.choice([-1.0, 1.0]) * rng.uniform(20.0, 30.0) * DEG,
    )


def run_icp(model: np.ndarray, data: np.ndarray, start: np.ndarray, config: ICPConfig) -> np.ndarray | None:
    try:
        return icp(model, data, start, config).transform
    except RegistrationError:  # too few pairs from a bad start counts as a failure
        return None


def evaluate(name, model, data, reference, shift, config, tolerance, rng, starts, rows) -> None:  # type: ignore[no-untyped-def]
    pivot = transform_points(reference, data).mean(axis=0)
    for _ in range(starts):
        offsets = random_offsets(rng, shift)
        start = offset_transform(reference, pivot, offsets)
        plain = run_icp(model, data, start, config)
        cpu, wall = time.process_time(), time.perf_counter()
        guess = octree_guess(model, data, start)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        refined = run_icp(model, data, guess.transform, config)

        def error(transform: np.ndarray | None) -> tuple[float, float]:
            if transform is None:
                return math.inf, math.inf
            metres, radians = pose_difference(transform, reference)
            return metres, radians / DEG

        rows.append(
            {
                "pair": name,
                "start": error(start),
                "plain": error(plain),
                "guess": error(guess.transform),
                "refined": error(refined),
                "ok_plain": error(plain)[0] < tolerance and error(plain)[1] < 0.5,
                "ok_refined": error(refined)[0] < tolerance and error(refined)[1] < 0.5,
                "cpu": cpu,
                "wall": wall,
                "candidates": sum(len(level.candidates) for level in guess.levels),
            }
        )
        row = rows[-1]
        print(
            f"{name:16s} start {row['start'][0]:6.3f} m {row['start'][1]:5.1f}°  plain {row['plain'][0]:7.4f} m"
            f" {row['plain'][1]:6.2f}°  guess {row['guess'][0]:6.4f} m {row['guess'][1]:5.2f}°"
            f"  guess+icp {row['refined'][0]:7.4f} m {row['refined'][1]:5.2f}°  cpu {cpu:5.2f} s wall {wall:5.2f} s"
            f"  {row['candidates']} candidates",
            flush=True,
        )


def summary(label: str, rows: list[dict]) -> None:
    if not rows:
        return
    plain_ok = sum(r["ok_plain"] for r in rows)
    refined_ok = sum(r["ok_refined"] for r in rows)
    print(
        f"{label}: {len(rows)} starts | plain ICP succeeds {plain_ok}/{len(rows)} | guess+ICP succeeds"
        f" {refined_ok}/{len(rows)} | guess error median {statistics.median(r['guess'][0] for r in rows):.4f} m"
        f" {statistics.median(r['guess'][1] for r in rows):.2f}° | guess cpu median"
        f" {statistics.median(r['cpu'] for r in rows):.2f} s, wall median {statistics.median(r['wall'] for r in rows):.2f} s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--starts", type=int, default=2, help="random starts per pair")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-bunny", action="store_true")
    parser.add_argument("--no-balm", action="store_true")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    root = data_root()
    balm_rows: list[dict] = []
    bunny_rows: list[dict] = []
    if not args.no_balm:
        for first, second in BALM_PAIRS:
            model, data = read_sequence(root / "balm_hall", first=first, last=second).scans
            reference = invert(model.pose) @ data.pose
            evaluate(f"balm {first}->{second}", model.points, data.points, reference, 1.0, ICPConfig(), 0.02, rng,
                     args.starts, balm_rows)  # fmt: skip
    if not args.no_bunny:
        scans = {scan.name: scan for scan in read_sequence(root / "stanford_bunny").scans}
        for model_name, data_name in BUNNY_PAIRS:
            model, data = scans[model_name], scans[data_name]
            reference = invert(model.pose) @ data.pose
            shift = 0.05 * cloud_extent(model.points)
            evaluate(f"{model_name}->{data_name}", model.points, data.points, reference, shift, BUNNY_ICP, 0.001, rng,
                     args.starts, bunny_rows)  # fmt: skip
    summary("BALM hall", balm_rows)
    summary("bunny", bunny_rows)


if __name__ == "__main__":
    main()
