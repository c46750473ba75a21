"""The workbench's jobs on the engine's Dask scheduler (``slam6d-workbench --scheduler``) land where they do without it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from slam6d.scheduler import DaskScheduler, SchedulerError
from tests.session_fixtures import corridor_session

ROOT = Path(__file__).resolve().parents[1]


def relaxed_poses(root: Path, scheduler: str | None) -> tuple[list[np.ndarray], int]:
    """Relax the corridor (LUM, scan 0 held) through the REST API: the poses, and the Dask workers the
    job's scheduler had (0: none); the scheduler is closed when the server stops."""
    with TestClient(create_app(root, viewers=False, scheduler=scheduler), base_url="http://127.0.0.1") as client:
        started = client.post("/api/sessions/corridor/relax", json={"method": "lum", "fixed": [0]})
        assert started.status_code == 202, started.text
        workbench = client.app.state.workbench  # type: ignore[attr-defined]
        job = workbench.jobs.wait(started.json()["id"], timeout=300)
        assert job.status == "done", job.message
        used = workbench.scheduler()
        workers = len(used.client.scheduler_info()["workers"]) if isinstance(used, DaskScheduler) else 0
        poses = workbench.current_poses("corridor")
    assert workbench._scheduler is None  # closed with the server
    return poses, workers


def test_a_relaxation_job_on_two_local_workers_gives_the_poses_of_one_without(tmp_path: Path) -> None:
    poses = {}
    for name, scheduler in (("here", None), ("cluster", "local:2")):
        root = tmp_path / name / "sessions"
        corridor_session(root, scans=5, points=6000, odometry_noise=0.1, engine={"voxel_size": 0.1})
        poses[name], workers = relaxed_poses(root, scheduler)
        assert workers == (0 if scheduler is None else 2)
    moved = max(float(np.abs(p - np.eye(4)).max()) for p in poses["here"])
    assert moved > 0  # the relaxation did something to compare
    for got, want in zip(poses["cluster"], poses["here"], strict=True):
        np.testing.assert_allclose(got, want, atol=1e-6)


def test_a_bad_scheduler_address_is_refused_when_the_server_starts(tmp_path: Path) -> None:
    with pytest.raises(SchedulerError, match="local:N"):
        create_app(tmp_path, viewers=False, scheduler="cluster")
    done = subprocess.run(
        [sys.executable, "-m", "app.main", "--sessions-dir", str(tmp_path), "--scheduler", "local:0"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2 and "local:N with N >= 1" in done.stderr


def test_a_workbench_without_scheduler_imports_nothing_of_dask(tmp_path: Path) -> None:
    check = (
        "import sys; from app.server import create_app; "
        f"app = create_app({str(tmp_path)!r}, viewers=False); "
        "assert app.state.workbench.scheduler() is None; "
        "print('dask loaded' if 'dask' in sys.modules else 'no dask')"
    )
    done = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "no dask"
