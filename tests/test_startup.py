"""What a `slam6d` command loads before it can work: every fresh process pays its imports, and on
the short sessions a user runs from the shell they are a large part of the command's time.

The command line itself loads no numerics at all; `slam6d run` loads the engine (numpy, numba and
the scipy.linalg numba takes its BLAS from, cvxopt, pykdtree) and none of the libraries only other
commands or fallbacks use: scipy's spatial and sparse modules, open3d (the feature guess), Dask
(``--scheduler``), rich (progress bars on a terminal), the renderer's video and image libraries.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.cli_process import HEAVY, ROOT, loaded_by


def test_importing_the_command_line_loads_no_numerics() -> None:
    code = f"import sys, slam6d.cli; print([m for m in {HEAVY!r} if m in sys.modules])"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert done.stdout.strip() == "[]"


def test_help_loads_no_numerics() -> None:
    assert loaded_by("run", "--help").isdisjoint({"numpy", "numba", "scipy", "open3d", "dask"})


def test_a_run_loads_the_engine_and_nothing_it_does_not_use(tmp_path: Path) -> None:
    from slam6d.simulate import SimulationConfig, simulate_session

    session = tmp_path / "loop"
    simulate_session(
        session, SimulationConfig(seed=2, scans=6, points_per_scan=20000, loop_length=16.0, loop_width=10.0)
    )
    loaded = loaded_by("run", str(session), "--format", "uos", "--out", str(tmp_path / "out"))
    assert (tmp_path / "out" / "poses_kitti.txt").exists()
    assert {"numpy", "numba"} <= loaded  # the hook saw the engine: the check below means something
    unused = {"scipy.spatial", "scipy.sparse", "open3d", "dask", "distributed", "rich", "matplotlib"}
    unused |= {"imageio", "imageio_ffmpeg", "PIL", "fastapi", "viser"}
    assert loaded.isdisjoint(unused), sorted(loaded & unused)
