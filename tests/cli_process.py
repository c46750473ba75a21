"""A `slam6d` command run in a fresh Python process that reports, as it ends, which heavy libraries
it had loaded: what the start-up tests and the scheduler's "no Dask without --scheduler" test check."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

HEAVY = (
    "numpy",
    "numba",
    "scipy",
    "scipy.linalg",
    "scipy.linalg.cython_blas",
    "scipy.spatial",
    "scipy.sparse",
    "open3d",
    "dask",
    "distributed",
    "rich",
    "matplotlib",
    "imageio",
    "imageio_ffmpeg",
    "PIL",
    "fastapi",
    "viser",
)

# `slam6d.cli.main` ends through `_leave`; the hook reports the loaded modules there, after the command
_REPORT_MODULES = (
    "import json, sys; sys.argv = ['slam6d'] + sys.argv[1:]; "
    "import slam6d.cli as cli; leave = cli._leave; "
    f"cli._leave = lambda code: (print(json.dumps([m for m in {HEAVY!r} if m in sys.modules])), leave(code)); "
    "cli.main()"
)


def python_result(code: str) -> dict[str, object]:
    """What a fresh Python process running ``code`` printed as JSON on its last line: a check of what
    a process imports has to start from one that has imported nothing yet."""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def loaded_by(*args: str) -> set[str]:
    """The heavy modules a `slam6d ARGS...` process had loaded when the command finished."""
    done = subprocess.run(
        [sys.executable, "-c", _REPORT_MODULES, *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return set(json.loads(done.stdout.strip().splitlines()[-1]))
