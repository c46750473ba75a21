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

With ``--profile-relaxation`` each session (dense loop and campus) is instead registered in this
process (loops closed, no relaxation), and ``slam6d run``'s LUM relaxation is then run on those
poses under ``cProfile`` (CPU time), its rounds and the ATE before and after it printed: its time
split into the rounds' closest-point queries and normal-equation blocks,
finding the bounded neighbour graph, gathering each scan's batch of neighbour points, the
inclinometer's prior where the folder declares one (as ``slam6d run`` holds it), and the
sparse linear algebra (working out the block pattern, factorising and solving) - the measurement
that decides whether the solve needs windows or a hierarchy (docs/scale.md) - and how many scan
pairs the neighbour graph counted overlap for at the registered poses (its cost, as a count).

``--stage-cpu`` instead runs each session's pipeline in this process as ``slam6d run`` configures
it and prints the CPU time (user + system, all threads) of each stage, the ATE and the load.

``--per-step N`` instead measures where the campus's height error comes from, on its first N scans:

* the cause: every consecutive pair matched from its TRUE relative pose by 15 point-to-plane steps
  against the registration model sequential matching uses (the scan reduced to 0.1 m, a 0.2 m
  plane sample, 0.35 m data points, 0.25 m pairs), with the model's normals taken three ways:
  0.4 m cubes alone (the registration's normals before the fix, k-NN where a cube gives none), the
  cubes of :func:`slam6d.normals.cell_normals` (0.4-3.2 m, k-NN where none holds a plane, as the
  registration model does), and the mesh's exact surface normals; and, as sequential registration
  now matches, against the metascan of the last three scans fused into one model at their true
  poses (:func:`slam6d.model.fused_model`: union reduced to 0.1 m, its own 0.2 m sample, cube
  normals and k-NN fallback over the union).
  Whatever the steps move away from the truth is the error of the cost itself; per model it prints
  the RMS per-step roll, pitch, yaw and height error and how many paired normals are more than 5°
  off the surface (not for the fused model, whose points were seen from three places);
* the effect: ``slam6d``'s sequential registration alone (no loops, no relaxation) over the same
  scans: per-step error RMS, and the ATE split into horizontal and vertical.

``--step-bias`` instead measures, on each dense loop of ``--loop``, the bias of sequential
registration along the motion (docs/scale.md, "Short steps: pairs off their planes"), three ways:
least squares (the default), the residual gate (``PipelineConfig.residual_gate``, ``--residual-gate``,
default 4 here) and Geman-McClure weights (``PipelineConfig.robust_scale``, ``--robust-scale``,
default 0.05 here):

* the cost: every consecutive pair matched from its TRUE relative pose by 15 point-to-plane steps
  against the previous scan's registration model, the pairs gated or weighted as the registration
  does once converged; the mean error along the step;
* the effect: sequential registration alone (no loops, no relaxation): the ATE and the mean and
  summed error of the estimated steps along the true ones.

``--loop-report`` adds, after each campus run, where its error lies and what the loops did, from
the files the run wrote and the simulator's ground truth: the ATE split into horizontal and
vertical after registration, after loop closing and after relaxation; the revisits of the truth
(scans within 10 m across and 2 m in height of one at least ``min_path`` back, grouped into
stretches; how many the loop stage tried, closed, and why it refused the others); and per closed
loop how far its verified transform is from the true relative pose and how far the final poses
keep it. ``--relax-from-truth`` instead runs ``slam6d run``'s relaxation (LUM with the run's models
and settings) from each campus session's ground truth and prints how far it moves away: the
relaxation's own bias, which no registration or loop closing upstream can remove.

Run: ``.venv/bin/python benchmarks/scale.py --work /tmp/scale --loop 100 200 400 --campus 250 500 1000``;
``.venv/bin/python benchmarks/scale.py --work /tmp/scale --loop 100 400 --campus 250 500 --profile-relaxation``;
``.venv/bin/python benchmarks/scale.py --work /tmp/scale --per-step 100``.
The figures measured so far, with their load, are in docs/scale.md; the campus runs (loops closed,
ATE and why it stays in metres) in docs/robustness.md, "Loops on the campus".
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks package beside the engine

from benchmarks.child_process import children_cpu
from slam6d import nn
from slam6d.geometry import UOS, Matrix, invert, path_lengths, pose_difference, transform_points
from slam6d.icp import gate_residuals, point_to_plane_step, robust_weights
from slam6d.io.frames import FrameType, read_frames
from slam6d.io.poses import read_kitti_poses
from slam6d.io.registry import read_sequence
from slam6d.metrics import absolute_trajectory_error, rigid_alignment
from slam6d.model import NORMAL_NEIGHBOURS, ModelIndex, fused_model
from slam6d.normals import cell_normals, estimate_normals
from slam6d.octree import reduce_points
from slam6d.pipeline import Pipeline, PipelineConfig
from slam6d.relax import RelaxationConfig
from slam6d.simulate import SimulationConfig, simulated_scans

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
    out: Path  # what the run wrote


def cli(*arguments: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "slam6d.cli", *arguments], capture_output=True, text=True, check=False)


def session(work: Path, case: str, scans: int) -> Path:
    directory = work / f"{case}{scans}"
    if not (directory / "ground_truth_kitti.txt").exists():
        done = cli("simulate", str(directory), "--scans", str(scans), "--overwrite", *CASES[case])
        if done.returncode != 0:
            raise SystemExit(f"slam6d simulate failed for {case} {scans}:\n{done.stderr}")
    return directory


def ground_truth(directory: Path) -> list[Matrix]:
    """The simulator's ground truth of a session folder, in the engine's canonical frame."""
    return [UOS.pose_to_canonical(p) for p in read_kitti_poses(directory / "ground_truth_kitti.txt")]


def registered_until_relaxation(directory: Path) -> tuple[PipelineConfig, Pipeline]:
    """``directory`` run as ``slam6d run`` runs it (its declared inclinometer) up to its relaxation:
    registered, loops closed, and the registration models handed to LUM's rounds as the relaxation
    stage hands them over (:func:`slam6d.pipeline.share_registration_models`)."""
    from slam6d.attitude import declared_tilt_noise
    from slam6d.pipeline import share_registration_models

    config = PipelineConfig(tilt_noise_deg=declared_tilt_noise(directory))
    pipeline = Pipeline(read_sequence(directory, "uos"), replace(config, relaxation="none"))
    pipeline.run()
    share_registration_models(pipeline.models, config, "lum", pipeline.registration_model)
    return config, pipeline


def run(directory: Path, case: str, scans: int, extra: list[str]) -> Run:
    out = directory.parent / f"{directory.name}_out{'_' + '_'.join(extra).replace('/', '') if extra else ''}"
    before = children_cpu()
    done = cli("run", str(directory), "--format", "uos", "--out", str(out), *extra)
    cpu = children_cpu() - before
    if done.returncode != 0:
        raise SystemExit(f"slam6d run failed on {directory}:\n{done.stdout}\n{done.stderr}")
    report = json.loads((out / "report.json").read_text())
    truth = ground_truth(directory)
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
        out,
    )


def scan_names(report: dict[str, Any]) -> list[str]:
    """The scans' names in order, as the run named their ``.frames`` files."""
    return [summary["name"] for summary in report["scan_summaries"]]


def unrelaxed_pose(frames: Path) -> np.ndarray:
    """A scan's last pose before relaxation: the newest entry of its history not written by it."""
    entries = read_frames(frames)
    return next(pose for pose, kind in reversed(entries) if kind not in (FrameType.LUM, FrameType.ICP_INACTIVE))


def registered_pose(frames: Path) -> np.ndarray:
    """A scan's pose as sequential registration left it: its last entry before any loop closing or relaxation."""
    entries = read_frames(frames)
    later = next((n for n, (_, kind) in enumerate(entries) if kind in LATER), len(entries))
    return entries[max(later, 1) - 1][0]


LATER = (FrameType.ELCH, FrameType.LUM)  # the stages after registration that write a scan's pose
REVISIT_ACROSS = 10.0  # metres: a truth revisit lies this close across ...
REVISIT_HEIGHT = 2.0  # ... and this close in height (the campus's street under its deck is 3.9 m below the roof)


def split_ate(estimate: list[Matrix], truth: list[Matrix]) -> str:
    """ATE rmse after rigid alignment, and its horizontal and vertical parts (cm)."""
    est, ref = np.array([p[:3, 3] for p in estimate]), np.array([p[:3, 3] for p in truth])
    alignment = rigid_alignment(est, ref)
    off = est @ alignment[:3, :3].T + alignment[:3, 3] - ref
    across, up = np.sqrt(np.mean((off[:, :2] ** 2).sum(axis=1))), np.sqrt(np.mean(off[:, 2] ** 2))
    return f"{100 * np.sqrt(across**2 + up**2):.1f} cm ({100 * across:.1f} across / {100 * up:.1f} height)"


def _closed_and_refused(hypotheses: list[dict[str, Any]]) -> str:
    """How many of ``hypotheses`` (a run report's loops) closed, and the tests the others failed, as
    two table cells."""
    reasons: dict[str, int] = {}
    for h in hypotheses:
        if not h["accepted"]:
            name = re.split(r"[\d(:]", h["reason"])[0].strip()  # the test, without its figures
            reasons[name] = reasons.get(name, 0) + 1
    refused = ", ".join(f"{k} ({v})" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])) or "-"
    return f"{sum(h['accepted'] for h in hypotheses)} | {refused}"


def loop_report(directory: Path, out: Path) -> None:
    """Where a campus run's error lies and what its loops did (module docstring, ``--loop-report``)."""
    report = json.loads((out / "report.json").read_text())
    names = scan_names(report)
    truth = ground_truth(directory)
    stages = {
        "registration": [UOS.pose_to_canonical(registered_pose(out / f"{n}.frames")) for n in names],
        "loop closing": [UOS.pose_to_canonical(unrelaxed_pose(out / f"{n}.frames")) for n in names],
        "relaxation": [UOS.pose_to_canonical(p) for p in read_kitti_poses(out / "poses_kitti.txt")],
    }
    print(f"\n{directory.name}: ATE after " + "; ".join(f"{k} {split_ate(v, truth)}" for k, v in stages.items()))
    settings = report["settings"]["loop"]
    where = np.array([p[:3, 3] for p in truth])
    travelled = path_lengths(truth)
    revisits: dict[int, bool] = {}  # revisiting scan -> whether it faces the other way than the place's first scan
    for j in range(len(truth)):
        gap = where[:j] - where[j]
        across = np.linalg.norm(gap[:, :2], axis=1)
        path = travelled[j] - travelled[:j]
        far_along = (path >= settings["min_path"]) & (path >= settings["min_path_factor"] * np.linalg.norm(gap, axis=1))
        near = np.flatnonzero((across < REVISIT_ACROSS) & (np.abs(gap[:, 2]) < REVISIT_HEIGHT) & far_along)
        if len(near):
            first = near[np.argmin(across[near])]
            revisits[j] = float(truth[first][:3, 0] @ truth[j][:3, 0]) < 0
    stretches: list[list[int]] = []
    for j in revisits:
        if stretches and j - stretches[-1][-1] <= 2:
            stretches[-1].append(j)
        else:
            stretches.append([j])
    print("| revisiting scans (truth) | of them the other way | tried | closed | refused for |")
    print("|---|---|---|---|---|")
    for stretch in stretches:
        hyps = [h for h in report["loops"] if h["j"] in stretch]
        label = f"{stretch[0]}-{stretch[-1]} ({len(stretch)})"
        print(f"| {label} | {sum(revisits[j] for j in stretch)} | {len(hyps)} | {_closed_and_refused(hyps)} |")
    elsewhere = [h for h in report["loops"] if h["j"] not in revisits]
    if elsewhere:
        print(f"| no revisit in the truth | | {len(elsewhere)} | {_closed_and_refused(elsewhere)} |")
    closed_loops = [h for h in report["loops"] if h["accepted"]]
    if not closed_loops:
        print("no loop closed")
        return
    verified, kept = [], []
    for h in closed_loops:
        true_relative = invert(truth[h["i"]]) @ truth[h["j"]]
        verified.append(pose_difference(np.array(h["transform"]), true_relative))
        final = stages["relaxation"]
        kept.append(pose_difference(invert(final[h["i"]]) @ final[h["j"]], true_relative))
    off = np.array(verified)
    held = np.array(kept)
    print(
        f"{len(closed_loops)} loops closed; verified transform vs the true relative pose: median"
        f" {100 * np.median(off[:, 0]):.1f} cm / {np.degrees(np.median(off[:, 1])):.2f}°, worst"
        f" {100 * off[:, 0].max():.1f} cm / {np.degrees(off[:, 1].max()):.2f}°; the final poses keep them to"
        f" {100 * np.median(held[:, 0]):.1f} cm median, {100 * held[:, 0].max():.1f} cm worst"
    )


RELAXATION_PARTS = {  # (module, function) whose cumulative time makes up each part of the split
    "rounds' queries and blocks": [("lum.py", "_scan_system"), ("lum.py", "_remote_scan_system")],
    "neighbour graph": [("relax.py", "neighbour_graph")],
    "batches of neighbour points": [("lum.py", "_batches")],
    "tilt prior": [("lum.py", "_add_tilt_prior")],
    "block pattern": [("block_system.py", "__init__")],
    "factorise and solve": [("block_system.py", "solve")],
}


def relax_from_truth(directory: Path) -> None:
    """``slam6d run``'s relaxation (its settings, models and links) started from the ground truth:
    how far the relaxation's own minimum lies from the truth, whatever registration and loop
    closing hand it."""
    from slam6d.pipeline import share_registration_models
    from slam6d.relaxation_methods import relax_poses

    config = PipelineConfig()
    pipeline = Pipeline(read_sequence(directory, "uos"), config)
    truth = ground_truth(directory)
    share_registration_models(pipeline.models, config, config.relaxation, pipeline.registration_model)
    links = [(k - 1, k) for k in range(1, len(truth))]  # what registration relates: each scan to the one before
    result = relax_poses(config.relaxation, pipeline.models, truth, links=links, config=config.relax)
    print(f"| {directory.name} | {split_ate(result.poses, truth)} | {result.iterations} | {os.getloadavg()[0]:.1f} |")


def profile_relaxation(directory: Path) -> None:
    """Register ``directory`` as ``slam6d run`` does up to its relaxation, then profile that relaxation."""
    import cProfile
    import pstats
    import time

    from slam6d.relax import neighbour_graph
    from slam6d.relaxation_methods import relax_poses

    config, pipeline = registered_until_relaxation(directory)
    profile = cProfile.Profile(time.process_time)  # CPU seconds: what the machine's other work inflates least
    began = time.process_time()
    profile.enable()
    result = relax_poses(
        "lum", pipeline.models, pipeline.poses, links=pipeline.links, config=config.relax, tilt=pipeline.tilt
    )
    profile.disable()
    seconds = time.process_time() - began
    truth = ground_truth(directory)
    ate = {
        "before": 100 * absolute_trajectory_error(pipeline.poses, truth).rmse,
        "after": 100 * absolute_trajectory_error(result.poses, truth).rmse,
    }
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
    # the graph's cost in a count: the scan pairs whose overlap it counted at the registered poses
    graph = neighbour_graph(
        pipeline.models,
        pipeline.poses,
        config.relax.min_pairs,
        links=pipeline.links,
        per_scan=config.relax.neighbours_per_scan,
    )
    scans = len(pipeline.poses)
    print(
        f"| {directory.name} | {scans} | {seconds:.1f} s | {result.iterations} | {len(result.neighbours):,}"
        f" | {graph.counted:,} ({graph.counted / scans:.1f} per scan) | {ate['before']:.2f} -> {ate['after']:.2f} cm"
        f" | {shares} | {os.getloadavg()[0]:.1f} |",
        flush=True,
    )


def relaxation_rounds(directory: Path, relax: RelaxationConfig) -> None:
    """Register ``directory`` as ``slam6d run`` does up to its relaxation, then run its LUM
    relaxation with the settings ``relax`` and print, after each round, the ATE and the path's
    length over the truth's: how fast the rounds close the distance (docs/scale.md, "Mixing the
    rounds")."""
    import time

    from slam6d.lum import lum_relaxation

    _, pipeline = registered_until_relaxation(directory)
    truth = ground_truth(directory)
    length = float(path_lengths(truth)[-1])
    rows: list[str] = []

    def observe(round_: int, poses: Sequence[Matrix]) -> None:
        ate = 100 * absolute_trajectory_error(list(poses), truth).rmse
        rows.append(f"{round_}: {ate:.2f} cm, length x{float(path_lengths(list(poses))[-1]) / length:.4f}")

    before = 100 * absolute_trajectory_error(pipeline.poses, truth).rmse
    began = time.process_time()
    result = lum_relaxation(
        pipeline.models, pipeline.poses, links=pipeline.links, config=relax, tilt=pipeline.tilt, observe=observe
    )
    seconds = time.process_time() - began
    print(
        f"| {directory.name} | {before:.2f} cm, length x{float(path_lengths(pipeline.poses)[-1]) / length:.4f}"
        f" | {'; '.join(rows)} | {result.iterations} | {seconds:.1f} s | {os.getloadavg()[0]:.1f} |",
        flush=True,
    )


def stage_cpu(directory: Path) -> None:
    """``slam6d run``'s pipeline on ``directory`` in this process (configured as the command line
    configures it for a folder: its declared inclinometer), with the CPU time (user + system of
    every thread) of each stage: what the machine's other work inflates least, split as the run's
    ``stage_seconds`` splits its wall time (each step counted to the stage that produced it)."""
    import time

    from slam6d.attitude import declared_tilt_noise

    began = time.process_time()
    sequence = read_sequence(directory, "uos")
    cpu = {"reading": time.process_time() - began}
    pipeline = Pipeline(sequence, PipelineConfig(tilt_noise_deg=declared_tilt_noise(directory)))
    cpu["reduction"] = time.process_time() - began - cpu["reading"]
    while not pipeline.done:
        start = time.process_time()
        pipeline.step()
        cpu[pipeline.stage] = cpu.get(pipeline.stage, 0.0) + time.process_time() - start
    total = time.process_time() - began
    truth = ground_truth(directory)
    ate = 100 * absolute_trajectory_error(pipeline.poses, truth).rmse
    stages = ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in cpu.items() if seconds >= 0.05)
    print(f"| {directory.name} | {total:.1f} s | {stages} | {ate:.3f} cm | {os.getloadavg()[0]:.1f} |", flush=True)


def step_errors(truth: list[Matrix], estimate: list[Matrix]) -> np.ndarray:
    """Per consecutive pair: the estimated relative motion's error against the true one, as
    (roll, pitch, yaw in degrees, height in cm) in the earlier scan's frame (z up)."""
    rows = []
    for k in range(1, len(truth)):
        error = invert(invert(truth[k - 1]) @ truth[k]) @ (invert(estimate[k - 1]) @ estimate[k])
        rows.append(step_error(error))
    return np.array(rows)


def step_error(error: Matrix) -> list[float]:
    r = error[:3, :3]
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    vector = axis * (angle / (2 * np.sin(angle))) if angle > 1e-12 else axis / 2
    return [*np.degrees(vector), 100 * error[2, 3]]


def rms_row(name: str, errors: np.ndarray, extra: str = "") -> str:
    roll, pitch, yaw, dz = np.sqrt(np.mean(errors**2, axis=0))
    return f"| {name} | {roll:.3f}° | {pitch:.3f}° | {yaw:.3f}° | {dz:.2f} cm |{extra}"


def from_truth(
    model: ModelIndex, data: np.ndarray, relative: Matrix, max_distance: float, gate: float = 0.0, robust: float = 0.0
) -> Matrix:
    """15 point-to-plane steps of ``data`` against ``model`` from the true relative pose (no stopping
    rule); ``gate`` > 0 leaves out the pairs as ``ICPConfig.residual_gate`` does, ``robust`` > 0
    weighs them as ``ICPConfig.robust_scale`` does (both apply once converged: here from the start)."""
    transform = relative.copy()
    for _ in range(15):
        moved = transform_points(transform, data)
        found, partners, _, normals = model.plane_pairs(moved, max_distance)
        if gate > 0:
            found, partners, normals = gate_residuals(moved[found], found, partners, normals, gate)
        weights = robust_weights(moved[found], partners, normals, robust) if robust > 0 else None
        transform = point_to_plane_step(moved[found], partners, normals, weights=weights) @ transform
    return transform


def along_steps(truth: list[Matrix], estimate: list[Matrix]) -> np.ndarray:
    """Per consecutive pair: the estimated step's translation error along the true step (m), in the
    earlier scan's frame; negative where the estimate falls short."""
    errors = []
    for k in range(1, len(truth)):
        step = invert(truth[k - 1]) @ truth[k]
        error = invert(step) @ invert(estimate[k - 1]) @ estimate[k]
        errors.append(float(error[:3, 3] @ step[:3, 3]) / float(np.linalg.norm(step[:3, 3])))
    return np.array(errors)


def step_bias(work: Path, scans: int, gate_on: float, robust_on: float) -> None:
    """The ``--step-bias`` rows of one dense loop (see the module docstring)."""
    directory = session(work, "loop", scans)
    sequence = read_sequence(directory, "uos")
    truth = ground_truth(directory)
    base = PipelineConfig(loops=False, relaxation="none")
    lengths = [float(np.linalg.norm((invert(truth[k - 1]) @ truth[k])[:3, 3])) for k in range(1, scans)]
    variants = {
        "least squares (default)": base,
        f"gate {gate_on:g}": replace(base, residual_gate=gate_on),
        f"Geman-McClure {100 * robust_on:g} cm": replace(base, robust_scale=robust_on),
    }
    for name, config in variants.items():
        run = Pipeline(sequence, config)
        run.run()
        pulls = []
        for k in range(1, scans):
            reduced = run.reduced_points(k)
            data = reduced[reduce_points(reduced, config.data_voxel_size)]
            relative = invert(truth[k - 1]) @ truth[k]
            model = run.registration_model(k - 1)
            fitted = from_truth(
                model, data, relative, config.icp.max_distance, config.residual_gate, config.robust_scale
            )
            pulls.append(along_steps([np.eye(4), relative], [np.eye(4), fitted])[0])
        along = along_steps(truth, [np.asarray(p) for p in run.poses])
        ate = 100 * absolute_trajectory_error(run.poses, truth).rmse
        print(
            f"| {scans} | {100 * np.mean(lengths):.1f} cm | {name} | {100 * np.mean(pulls):+.3f} cm"
            f" | {100 * np.mean(along):+.3f} cm | {100 * np.sum(along):+.1f} cm | {ate:.2f} cm |",
            flush=True,
        )


def per_step(work: Path, scans: int) -> None:
    """The ``--per-step`` tables (see the module docstring)."""
    config = SimulationConfig(seed=3, scans=scans, points_per_scan=20000, world="campus")
    simulation = simulated_scans(config)
    clouds = list(simulation.scans())
    truth = simulation.truth
    pipeline = PipelineConfig()
    voxel, cell = pipeline.voxel_size, pipeline.normal_cell_voxels * pipeline.voxel_size
    sample_voxel, data_voxel = pipeline.sample_voxels * voxel, pipeline.data_voxel_size
    max_distance = pipeline.icp.max_distance
    sources = ("0.4 m cubes (before)", "0.4-3.2 m cubes", "mesh surface normals")
    fused_name = f"{pipeline.fused_scans} scans fused, 0.4-3.2 m cubes (now)"
    errors: dict[str, list[list[float]]] = {name: [] for name in sources}
    off: dict[str, list[float]] = {name: [] for name in sources}
    for k in range(1, scans):
        reduced = clouds[k - 1][reduce_points(clouds[k - 1], voxel)]
        sample = reduce_points(reduced, sample_voxel)
        points = reduced[sample]
        index = nn.build_index(points, nn.DEFAULT_BACKEND, 2)
        directions = points / np.linalg.norm(points, axis=1, keepdims=True)
        surface = simulation.scene.surface_normals(truth[k - 1][:3, 3], directions @ truth[k - 1][:3, :3].T)
        surface = surface @ truth[k - 1][:3, :3]  # into the scanner's frame
        knn, knn_ok = estimate_normals(index, points, NORMAL_NEIGHBOURS)
        old, old_ok = cell_normals(reduced, cell, levels=1, min_spread=0.0, max_thickness=1.0)
        new, new_ok = cell_normals(reduced, cell)
        normals = {
            sources[0]: (np.where(old_ok[sample, None], old[sample], knn), old_ok[sample] | knn_ok),
            sources[1]: (np.where(new_ok[sample, None], new[sample], knn), new_ok[sample] | knn_ok),
            sources[2]: (surface, np.ones(len(points), dtype=np.bool_)),
        }
        data_all = clouds[k][reduce_points(clouds[k], voxel)]
        data = data_all[reduce_points(data_all, data_voxel)]
        relative = invert(truth[k - 1]) @ truth[k]
        members = range(max(0, k - pipeline.fused_scans), k)
        fused = fused_model(
            [clouds[j][reduce_points(clouds[j], voxel)] for j in members],
            [truth[j] for j in members],
            NORMAL_NEIGHBOURS,
            sample_voxel,
            normal_cell=cell,
            voxel_size=voxel,
        )
        errors.setdefault(fused_name, []).append(
            step_error(invert(relative) @ from_truth(fused, data, relative, max_distance))
        )
        for name, (n, usable) in normals.items():
            transform = relative.copy()
            paired = np.zeros(len(points), dtype=np.bool_)
            for _ in range(15):
                moved = transform_points(transform, data)
                _, partner = index.nearest(moved, max_distance)
                found = np.flatnonzero(partner >= 0)
                found = found[usable[partner[found]]]
                paired[partner[found]] = True
                transform = point_to_plane_step(moved[found], points[partner[found]], n[partner[found]]) @ transform
            errors[name].append(step_error(invert(relative) @ transform))
            cosine = np.abs(np.einsum("ij,ij->i", n[paired], surface[paired]))
            off[name].append(float(np.mean(cosine < np.cos(np.radians(5.0)))))
    print(f"campus, first {scans} scans: each consecutive pair matched from its true relative pose (RMS per step)")
    print("| model normals | roll | pitch | yaw | height | paired normals > 5° off the surface |")
    print("|---|---|---|---|---|---|")
    for name in sources:
        print(rms_row(name, np.array(errors[name]), f" {100 * np.mean(off[name]):.0f} % |"))
    print(rms_row(fused_name, np.array(errors[fused_name]), " - |"))
    directory = session(work, "campus", scans)
    sequence = read_sequence(directory, "uos")
    run = Pipeline(sequence, PipelineConfig(loops=False, relaxation="none"))
    run.run()
    estimate = [np.asarray(p) for p in run.poses]
    truth_files = ground_truth(directory)
    positions = np.array([p[:3, 3] for p in estimate])
    reference = np.array([p[:3, 3] for p in truth_files])
    alignment = rigid_alignment(positions, reference)
    apart = positions @ alignment[:3, :3].T + alignment[:3, 3] - reference
    horizontal = 100 * np.sqrt(np.mean(np.sum(apart[:, :2] ** 2, axis=1)))
    vertical = 100 * np.sqrt(np.mean(apart[:, 2] ** 2))
    print(f"\nsequential registration alone (slam6d, no loops, no relaxation) over the same {scans} scans")
    print("| | roll | pitch | yaw | height | ATE (horizontal / vertical) |")
    print("|---|---|---|---|---|---|")
    ate = 100 * absolute_trajectory_error(estimate, truth_files).rmse
    print(
        rms_row("per step", step_errors(truth_files, estimate), f" {ate:.1f} cm ({horizontal:.1f} / {vertical:.1f}) |")
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
        "--residual-gate",
        type=float,
        default=0.0,
        help="passed to slam6d run (e.g. 4); with --step-bias the gate compared with none (default 4)",
    )
    parser.add_argument(
        "--robust-scale",
        type=float,
        default=0.0,
        help="passed to slam6d run (e.g. 0.05); with --step-bias the scale compared with none (default 0.05)",
    )
    parser.add_argument(
        "--profile-relaxation", action="store_true", help="profile LUM relaxation on the sessions instead"
    )
    parser.add_argument("--per-step", type=int, metavar="N", help="only the campus's per-step error tables on N scans")
    parser.add_argument(
        "--step-bias",
        action="store_true",
        help="only: the dense loops' bias along each step, least squares, gate and weights",
    )
    parser.add_argument(
        "--loop-report", action="store_true", help="after each campus run: its error by stage, revisits and loops"
    )
    parser.add_argument(
        "--stage-cpu", action="store_true", help="only: each session's run in this process, CPU time per stage"
    )
    parser.add_argument(
        "--relax-from-truth", action="store_true", help="only: the run's relaxation started from the campus's truth"
    )
    parser.add_argument(
        "--rounds", action="store_true", help="only: each session's LUM relaxation, its error after every round"
    )
    parser.add_argument(
        "--relax",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="with --rounds: a RelaxationConfig setting, e.g. acceleration_depth=0 (repeatable)",
    )
    parser.add_argument(
        "--sessions",
        type=Path,
        nargs="*",
        default=[],
        help="with --rounds: these simulated folders (uos, with ground_truth_kitti.txt) instead of --loop/--campus",
    )
    args = parser.parse_args()
    if args.rounds:
        from benchmarks.trajectory import relax_settings

        print("| session | start | after each round | rounds | CPU | load |")
        print("|---|---|---|---|---|---|")
        folders = args.sessions or [
            session(args.work, case, scans)
            for case, counts in (("loop", args.loop), ("campus", args.campus))
            for scans in counts
        ]
        for folder in folders:
            relaxation_rounds(folder, relax_settings(args.relax))
        return
    if args.profile_relaxation:
        print(f"LUM relaxation under cProfile, CPU seconds, {os.cpu_count()} cores (cProfile itself adds some)")
        print(
            "| session | scans | relaxation | rounds | neighbour pairs | overlaps counted | ATE before -> after | of it"
            " | load |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for case, counts in (("loop", args.loop), ("campus", args.campus)):
            for scans in counts:
                profile_relaxation(session(args.work, case, scans))
        return
    if args.stage_cpu:
        print(f"slam6d run's pipeline in one process, CPU seconds per stage, {os.cpu_count()} cores")
        print("| session | CPU | per stage | ATE | load |")
        print("|---|---|---|---|---|")
        for case, counts in (("loop", args.loop), ("campus", args.campus)):
            for scans in counts:
                stage_cpu(session(args.work, case, scans))
        return
    if args.relax_from_truth:
        print("| session | ATE after relaxing the truth (across / height) | rounds | load |")
        print("|---|---|---|---|")
        for scans in args.campus:
            relax_from_truth(session(args.work, "campus", scans))
        return
    if args.per_step:
        per_step(args.work, args.per_step)
        return
    if args.step_bias:
        print("dense loop: error along each step (negative: short), from the truth and by sequential registration")
        print("| scans | step | registration | from the truth, mean | registration, mean | summed | ATE |")
        print("|---|---|---|---|---|---|---|")
        for scans in args.loop:
            step_bias(args.work, scans, args.residual_gate or 4.0, args.robust_scale or 0.05)
        return
    extra = ["--memory-budget", args.memory_budget] if args.memory_budget else []
    if args.residual_gate:
        extra += ["--residual-gate", str(args.residual_gate)]
    if args.robust_scale:
        extra += ["--robust-scale", str(args.robust_scale)]
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
            if args.loop_report and case == "campus":
                loop_report(directory, r.out)
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
