"""Timing a command as the user's shell runs it: a fresh child process on one checkout of the engine.

``slam6d run`` is a command, and on short sessions its start-up is a large part of it, so the
benchmarks that compare it with a peer's chain (``command_time.py``, ``robustness.py``) or split its
start-up (``startup.py``) time it as a child process and read its CPU time (user + system) from the
finished children's usage: CPU is the figure that survives a loaded machine. ``--against`` times
another checkout in alternation with this one, process by process, so both see the same load.
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

CHAIN_STARTUP = "import numpy as np, small_gicp; small_gicp.PointCloud(np.zeros((10, 3)))"
"""What a script running the small_gicp chain as its own command pays before its first scan."""


class Cost(NamedTuple):
    """Seconds one child process took: on the wall clock, and of CPU (user + system)."""

    wall: float
    cpu: float


def children_cpu() -> float:
    """CPU seconds (user + system) of the finished child processes so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed_command(command: list[str], tree: Path = ROOT) -> Cost:
    """The cost of one child process running ``command`` on the engine in ``tree`` (its working
    directory and first on its path); it must succeed, else its error output is raised."""
    wall, cpu = time.perf_counter(), children_cpu()
    done = subprocess.run(command, capture_output=True, text=True, cwd=tree, env=os.environ | {"PYTHONPATH": str(tree)})
    if done.returncode != 0:
        raise RuntimeError(f"{command[:4]} exit {done.returncode}: {done.stderr[-2000:]}")
    return Cost(time.perf_counter() - wall, children_cpu() - cpu)


def add_against_option(parser: argparse.ArgumentParser, timed: str) -> None:
    """``--against CHECKOUT``: ``timed`` (what is measured) also on another checkout, in alternation."""
    parser.add_argument(
        "--against",
        type=Path,
        help=f"another checkout (git worktree add ../before COMMIT) whose {timed} is measured in alternation"
        " with this one's, process by process, so both see the same load",
    )


def checkouts(against: Path | None) -> list[Path]:
    """This checkout, and ``against`` when given, each with its engine's bytecode written first as an
    install writes it (otherwise the first process of each would pay the compilation)."""
    trees = [ROOT] if against is None else [ROOT, against.resolve()]
    for tree in trees:
        compileall.compile_dir(tree / "slam6d", quiet=1)
    return trees


class RunOutput(NamedTuple):
    """What a `slam6d run` child process left: its poses as written (the input's own frame and
    units), its exit code, and when it failed (exit code not 0) the reason ``report.json`` gives."""

    poses: list[np.ndarray]
    returncode: int
    failure: str


def run_slam6d(source: Path, args: Sequence[str] = (), tree: Path = ROOT) -> RunOutput:
    """`slam6d run SOURCE --out TMP ARGS` of the checkout ``tree`` as a user starts it: a new process
    reading the files and writing its results. A run whose stage failed still wrote its poses (exit
    3), and they are returned with the reason; a run that wrote none raises its error output."""
    from slam6d.io.poses import read_kitti_poses  # the engine of this checkout, for reading only

    with tempfile.TemporaryDirectory() as out:
        command = [sys.executable, "-m", "slam6d.cli", "run", str(source), "--out", out, *args]
        done = subprocess.run(
            command, capture_output=True, text=True, cwd=tree, env=os.environ | {"PYTHONPATH": str(tree)}
        )
        poses_file = Path(out) / "poses_kitti.txt"
        if not poses_file.exists():
            raise RuntimeError(f"{source}: exit {done.returncode}: {done.stderr.strip().splitlines()[-1:]}")
        failure = ""
        if done.returncode != 0:
            report = json.loads((Path(out) / "report.json").read_text())
            failure = str(report.get("failure", {}).get("reason", ""))
        return RunOutput(read_kitti_poses(poses_file), done.returncode, failure)
