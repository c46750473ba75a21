"""One engine behind both doors: the workbench's relaxation and ``slam6d relax`` give the same poses
on the same session and graph, for every method, and ``slam6d run --relaxation graph`` runs."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from app.server import create_app
from slam6d.cli import app as cli
from slam6d.io.poses import read_kitti_poses
from slam6d.session import Session
from tests.session_fixtures import corridor_session

CORRIDOR = "/api/sessions/corridor"


@pytest.fixture
def edited_session(tmp_path):
    """A corridor session whose graph was edited in the workbench (an ICP-refined edge 0-3 added)."""
    root = tmp_path / "sessions"
    corridor_session(root, scans=4, points=3000, odometry_noise=0.1, engine={"voxel_size": 0.1})
    with TestClient(create_app(root, viewers=False)) as client:
        assert client.post(f"{CORRIDOR}/edges", json={"i": 0, "j": 3}).status_code == 201
    return root


@pytest.mark.parametrize("method", ["lum", "graph", "simultaneous"])
def test_the_workbench_and_the_cli_relax_a_session_to_the_same_poses(edited_session, tmp_path, method):
    copy = tmp_path / "copy"
    shutil.copytree(edited_session / "corridor", copy)

    with TestClient(create_app(edited_session, viewers=False)) as client:
        response = client.post(f"{CORRIDOR}/relax", json={"method": method, "fixed": [0]})
        assert response.status_code == 202, response.text
        job = client.app.state.workbench.jobs.wait(response.json()["id"], timeout=120)
        assert job.status == "done", job.message
        from_workbench = client.app.state.workbench.current_poses("corridor")

    out = tmp_path / "relaxed.txt"
    result = CliRunner().invoke(cli, ["relax", str(copy), "--method", method, "--out", str(out), "--commit"])
    assert result.exit_code == 0, result.output
    from_cli = read_kitti_poses(out)

    before = Session.open(copy).get_revision(1).poses
    assert max(np.abs(a - b).max() for a, b in zip(before, from_cli, strict=True)) > 1e-3  # it did relax
    for a, b in zip(from_workbench, from_cli, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)
    stored = Session.open(copy)
    assert stored.journal.entries()[-1].kind == f"relax_{method}"
    for a, b in zip(stored.poses(), from_cli, strict=True):  # --commit stored what --out wrote
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_graph_relaxation_is_selectable_from_slam6d_run(tmp_path):
    corridor_session(tmp_path / "sessions", scans=4, points=3000, odometry_noise=0.1)
    scans = tmp_path / "sessions" / "corridor" / "scans"
    result = CliRunner().invoke(
        cli, ["run", str(scans), "--format", "uos", "--relaxation", "graph", "--out", str(tmp_path / "out")]
    )
    assert result.exit_code == 0, result.output
    assert "relaxation (graph)" in result.output
    assert len(read_kitti_poses(tmp_path / "out" / "poses_kitti.txt")) == 4


def test_an_unknown_relaxation_is_refused_by_name(tmp_path):
    corridor_session(tmp_path / "sessions", scans=3, points=500)
    scans = tmp_path / "sessions" / "corridor" / "scans"
    result = CliRunner().invoke(cli, ["run", str(scans), "--relaxation", "magic", "--out", str(tmp_path / "out")])
    assert result.exit_code != 0 and "relaxation must be one of" in result.output
    refused = CliRunner().invoke(cli, ["relax", str(tmp_path / "sessions" / "corridor"), "--method", "magic"])
    assert refused.exit_code != 0 and "unknown relaxation 'magic'" in str(refused.exception)
