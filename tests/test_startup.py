"""What a `slam6d` command loads before it can work: every fresh process pays its imports, and on
the short sessions a user runs from the shell they are a large part of the command's time.

The command line itself loads no numerics at all; `slam6d run` loads the engine (numpy, numba,
cvxopt, pykdtree) with scipy's BLAS bindings that numba checks for, but not the scipy.linalg package
around them (``slam6d.numba_blas``), and none of the libraries only other commands or fallbacks use:
scipy's spatial and sparse modules, open3d (the feature guess), Dask (``--scheduler``), rich
(progress bars on a terminal), the renderer's video and image libraries.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.cli_process import HEAVY, ROOT, loaded_by, python_result


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
    # the hook saw the engine, and numba's BLAS check found its bindings: the check below means something
    assert {"numpy", "numba", "scipy.linalg.cython_blas"} <= loaded
    unused = {"scipy.linalg", "scipy.spatial", "scipy.sparse", "open3d", "dask", "distributed", "rich", "matplotlib"}
    unused |= {"imageio", "imageio_ffmpeg", "PIL", "fastapi", "viser"}
    assert loaded.isdisjoint(unused), sorted(loaded & unused)


_BLAS_WITHOUT_LINALG = """
import json, sys
import numpy as np, numba
from slam6d.numba_blas import BLAS_BINDINGS, load_blas_bindings

loaded = load_blas_bindings()
bindings = sys.modules[BLAS_BINDINGS]

@numba.njit(cache=False)  # compiled here: numba's BLAS path itself, not a cached kernel
def product(a, b):
    return np.dot(a, b)

a, b = np.arange(9.0).reshape(3, 3), np.arange(9.0, 18.0).reshape(3, 3)
dot_ok = bool(np.allclose(product(a, b), a @ b))
linalg_before = "scipy.linalg" in sys.modules
from numba.np import arraymath

import scipy.linalg
from scipy.linalg import cython_blas

solved = scipy.linalg.solve(np.diag([2.0, 4.0, 8.0]), np.ones(3))
print(json.dumps({
    "loaded": loaded, "again": load_blas_bindings(), "linalg_before": linalg_before,
    "numba_has_blas": arraymath._HAVE_BLAS, "dot_ok": dot_ok, "same_module": cython_blas is bindings,
    "solved": solved.tolist(),
}))
"""


def test_numba_gets_its_blas_without_the_scipy_linalg_package() -> None:
    result = python_result(_BLAS_WITHOUT_LINALG)
    assert result["loaded"] is True and result["again"] is False
    assert result["linalg_before"] is False  # numba's first call (a compilation, even) left it out
    assert result["numba_has_blas"] is True and result["dot_ok"] is True
    # scipy.linalg imported afterwards works and uses the very bindings loaded before it
    assert result["same_module"] is True
    assert result["solved"] == [0.5, 0.25, 0.125]


def test_the_bindings_are_left_alone_once_scipy_linalg_is_loaded() -> None:
    code = (
        "import json, sys, scipy.linalg; from slam6d.numba_blas import BLAS_BINDINGS, load_blas_bindings; "
        "before = sys.modules.get(BLAS_BINDINGS); loaded = load_blas_bindings(); "
        "print(json.dumps({'loaded': loaded, 'untouched': sys.modules.get(BLAS_BINDINGS) is before}))"
    )
    assert python_result(code) == {"loaded": False, "untouched": True}
