"""Relaxing a registered session again, with and without the odometry's inclinometer: ATE and tilt.

``slam6d run`` holds every scan's "up" to the inclinometer's readings where the input declares one
(docs/cli.md, "An inclinometer"). A session's revision is relaxed again by ``slam6d relax`` or the
workbench's Relax, which hold the same readings (revision 0, the odometry) where the session's
``[engine] tilt_noise_deg`` declares them (:mod:`slam6d.session_relaxation`). This measures what
that is worth: a session is made over a simulated folder (``slam6d simulate``) whose current
revision is what ``slam6d run`` wrote for it (as a workbench registration job would store it), then
``slam6d relax SESSION --out FILE`` runs twice, with the session's declaration and with
``--tilt-noise-deg 0``, each the command line a user starts. Printed per pose set (the run's, and
each relaxation's): ATE against the simulator's ground truth after rigid alignment, split into
across and height; each scan's tilt (the angle between its "up" and the true one, no alignment:
both frames share gravity) as RMS and max; the tilt off the readings as RMS and how many scans
lie farther from their reading than the declared noise; and the relaxation's wall time with the
load average, since the machine may be shared.

LUM pairs against the scans' registration models (per-cube normals, a 0.2 m plane sample), as
``slam6d run``'s own relaxation does (:func:`slam6d.pipeline.share_registration_models`); before
they did, ``slam6d relax`` paired against the k-NN normals of the reduced scans and undid the
run's map (docs/scale.md).

Run: ``.venv/bin/python benchmarks/tilt_relax.py --scans /tmp/campus250 --run /tmp/c250 --work /tmp/tilt_relax``
after ``slam6d simulate /tmp/campus250 --world campus --scans 250 --points-per-scan 20000 --seed 3``
and ``slam6d run /tmp/campus250 --format uos --out /tmp/c250``. Figures: docs/scale.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from slam6d.attitude import declared_tilt_noise, measured_up, tilt_error_deg
from slam6d.geometry import UOS, Matrix
from slam6d.io.poses import read_kitti_poses
from slam6d.metrics import rigid_alignment
from slam6d.session import Session


def relax(session: Path, out: Path, *extra: str) -> tuple[float, str]:
    """``slam6d relax SESSION --out OUT`` as a user runs it: (wall seconds, what it printed)."""
    began = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "slam6d.cli", "relax", str(session), "--out", str(out), *extra],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise SystemExit(f"slam6d relax failed:\n{done.stdout}\n{done.stderr}")
    return time.perf_counter() - began, done.stdout.strip()


def row(name: str, poses: list[Matrix], truth: list[Matrix], readings: list[Matrix], noise: float, extra: str) -> str:
    est, ref = np.array([p[:3, 3] for p in poses]), np.array([p[:3, 3] for p in truth])
    alignment = rigid_alignment(est, ref)
    off = est @ alignment[:3, :3].T + alignment[:3, 3] - ref
    across, height = np.sqrt(np.mean((off[:, :2] ** 2).sum(axis=1))), np.sqrt(np.mean(off[:, 2] ** 2))
    tilt = np.array([tilt_error_deg(p, measured_up(t)) for p, t in zip(poses, truth, strict=True)])
    from_reading = np.array([tilt_error_deg(p, measured_up(r)) for p, r in zip(poses, readings, strict=True)])
    return (
        f"| {name} | {100 * np.hypot(across, height):.2f} cm ({100 * across:.2f} / {100 * height:.2f}) "
        f"| {np.sqrt(np.mean(tilt**2)):.3f}° / {tilt.max():.3f}° "
        f"| {np.sqrt(np.mean(from_reading**2)):.3f}° / {int(np.sum(from_reading > noise))} of {len(poses)} "
        f"| {extra} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", type=Path, required=True, help="a folder written by slam6d simulate (uos)")
    parser.add_argument("--run", type=Path, required=True, help="what slam6d run wrote for it (poses_kitti.txt)")
    parser.add_argument("--work", type=Path, required=True, help="where the session is made (replaced)")
    args = parser.parse_args()
    noise = declared_tilt_noise(args.scans)
    if noise is None:
        raise SystemExit(f"{args.scans} declares no inclinometer (simulation.json): nothing to compare")
    folder = args.work / "session"
    if folder.exists():
        shutil.rmtree(folder)
    session = Session.create(folder, "tilt relax", args.scans.resolve())
    registered = [UOS.pose_to_canonical(p) for p in read_kitti_poses(args.run / "poses_kitti.txt")]
    session.load_sequence()  # revision 0: the odometry the files carry, the inclinometer's readings
    session.journal.commit(registered, "benchmark", "register", {"from": "slam6d run"})
    readings, truth = (
        session.poses(0),
        [UOS.pose_to_canonical(p) for p in read_kitti_poses(args.scans / "ground_truth_kitti.txt")],
    )
    rows = [row("`slam6d run`", registered, truth, readings, noise, "")]
    for name, extra in (("relaxed, readings held", ()), ("relaxed, `--tilt-noise-deg 0`", ("--tilt-noise-deg", "0"))):
        out = args.work / f"relaxed{'_off' if extra else ''}.txt"
        seconds, said = relax(folder, out, *extra)
        print(said, file=sys.stderr)
        rows.append(
            row(name, read_kitti_poses(out), truth, readings, noise, f"{seconds:.1f} s, load {os.getloadavg()[0]:.1f}")
        )
    print(f"{len(truth)} scans, inclinometer {noise:g}° declared")
    print(
        "| poses | ATE (across / height) | tilt off the truth RMS / max | off the reading RMS / scans > noise | relax |"
    )
    print("|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
