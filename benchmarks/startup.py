"""What a `slam6d run` process costs before its first scan, phase by phase.

Every command is a fresh Python process, and on the short sessions a user runs from the shell the
start-up is a large part of the command: a 10-scan session's small_gicp chain takes 0.1-0.9 s of CPU
(``benchmarks/robustness.py``). Each row here is a fresh process doing every phase above it and its
own; the table gives each phase's share (median CPU, user + system, and median wall time over
``--repeats`` processes, interleaved) and the whole ``slam6d run`` of a simulated 10-scan session
without odometry last. Almost all of it is Python holding the GIL, so wall time is CPU time plus
waiting for a core; CPU is the figure that survives a loaded machine.

Phases: the interpreter; importing the command line (typer); parsing ``run``'s options as the
command does (typer 0.29 imports pydantic and builds a pydantic ``TypeAdapter`` for every option
that is not a flag); the formats registry with numpy; numba's import; the engine's modules; numba's
first call (it loads its typing and lowering registries once per process, with scipy's BLAS
bindings loaded alone first, as ``slam6d run`` does: ``slam6d.numba_blas``; two kernels then load
from the cache).

The engine's bytecode is written first (``make bytecode``), as an install writes it; numba's
kernels must be compiled already (``make kernels``, or any earlier run), else the first row that
calls one pays the compilation.

    .venv/bin/python benchmarks/startup.py [--repeats 7] [--against ../before]

``--against`` measures another checkout (``git worktree add ../before COMMIT``) in alternation with
this one, each process of one followed by the same process of the other, so both see the same load.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.child_process import add_against_option, checkouts, timed_command  # noqa: E402
from benchmarks.trajectory import load  # noqa: E402

FIRST_CALL = """
import numpy as np
try:
    from slam6d.numba_blas import load_blas_bindings
except ImportError:  # a checkout from before it (--against)
    pass
else:
    load_blas_bindings()
from slam6d.octree import reduce_points
reduce_points(np.zeros((10, 3)), 0.1)
"""
"""numba's first call as ``slam6d run`` makes it (``benchmarks/robustness.py`` counts it in the
start-up it takes off the run's CPU time)."""


def phases(session: Path, out: Path) -> list[tuple[str, str]]:
    """(name, code) of each phase; a phase's process runs the code of every phase up to it."""
    args = [str(session), "--format", "uos", "--out", str(out)]
    return [
        ("interpreter", "pass"),
        ("command line (typer)", "import slam6d.cli as cli"),
        (
            "run's options (typer: pydantic, a TypeAdapter each)",
            f"import typer; typer.main.get_command(cli.app).commands['run'].make_context('run', {args!r})",
        ),
        ("formats registry (numpy)", "import slam6d.io.registry"),
        ("numba import", "import numba"),
        ("engine modules", "import slam6d.pipeline, slam6d.engine_settings, slam6d.posegraph, slam6d.scheduler"),
        ("numba's first call (its registries)", FIRST_CALL),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7, help="processes per phase (the median is shown)")
    add_against_option(parser, "start-up")
    args = parser.parse_args()
    trees = checkouts(args.against)
    with tempfile.TemporaryDirectory() as tmp:
        session, out = Path(tmp) / "session", Path(tmp) / "out"
        simulate = ["simulate", str(session), "--world", "outdoor", "--sensor", "vlp16", "--scans", "10", "--seed", "1"]
        timed_command([sys.executable, "-m", "slam6d.cli", *simulate, "--no-odometry"], ROOT)
        run = [sys.executable, "-m", "slam6d.cli", "run", str(session), "--format", "uos", "--out", str(out)]
        for tree in trees:
            timed_command(run, tree)  # compiles any kernel not cached yet
        steps = phases(session, out)
        commands = [[sys.executable, "-c", "\n".join(code for _, code in steps[: k + 1])] for k in range(len(steps))]
        commands.append(run)
        # [tree][command] -> CPU and wall seconds of each repeat
        cpu: list[list[list[float]]] = [[[] for _ in commands] for _ in trees]
        wall: list[list[list[float]]] = [[[] for _ in commands] for _ in trees]
        for _ in range(args.repeats):
            for k, command in enumerate(commands):
                for t, tree in enumerate(trees):
                    cost = timed_command(command, tree)
                    cpu[t][k].append(cost.cpu)
                    wall[t][k].append(cost.wall)
    print(f"Seconds of a fresh process, median of {args.repeats} ({load()})")
    for t, tree in enumerate(trees):
        cpu_medians = [statistics.median(c) for c in cpu[t]]
        wall_medians = [statistics.median(w) for w in wall[t]]
        print(f"{tree}:" if len(trees) > 1 else "")
        print(f"  {'phase':55s} {'CPU':>6s} {'wall':>6s}   cumulative CPU, wall")
        previous = (0.0, 0.0)
        for (name, _), cumulative in zip(steps, zip(cpu_medians, wall_medians, strict=True), strict=False):
            print(
                f"  {name:55s} {cumulative[0] - previous[0]:6.3f} {cumulative[1] - previous[1]:6.3f}"
                f"   ({cumulative[0]:.3f}, {cumulative[1]:.3f})"
            )
            previous = cumulative
        last_rows = (("before the first scan", len(steps) - 1), ("slam6d run, 10-scan outdoor VLP-16, no odometry", -1))
        for name, k in last_rows:
            print(f"  {name:55s} {cpu_medians[k]:6.3f} {wall_medians[k]:6.3f}")


if __name__ == "__main__":
    main()
