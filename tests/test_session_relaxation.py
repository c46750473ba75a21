"""Relaxing a session again holds the odometry's inclinometer where the session declares one
(slam6d.session_relaxation): ``slam6d relax`` and the workbench's Relax job alike, the readings
taken from revision 0, and nothing changes for a session that declares none."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from app.server import create_app
from slam6d.attitude import measured_up, tilt_error_deg
from slam6d.cli import app as cli
from slam6d.engine_settings import pipeline_config
from slam6d.errors import SessionError
from slam6d.geometry import UOS, Matrix, invert, pose_from_xyzrpy
from slam6d.io.poses import read_kitti_poses
from slam6d.loops import LoopHypothesis
from slam6d.metrics import absolute_trajectory_error
from slam6d.relaxation_methods import reduced_models
from slam6d.session import Session
from slam6d.session_relaxation import close_revision_loops, relax_revision
from slam6d.simulate import SimulationConfig, simulate_session
from tests.session_fixtures import corridor_session

NOISE_DEG = 0.05  # a good IMU's gravity estimate: the readings then stand clearly apart from the pairs' drift


@pytest.fixture(scope="module")
def campus(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """20 campus scans (a car's VLP-16, whose ring pairs hold a biased relative tilt) whose odometry
    carries an inclinometer of ``NOISE_DEG``, declared in simulation.json."""
    folder = tmp_path_factory.mktemp("campus") / "scans"
    config = SimulationConfig(
        world="campus", scans=20, points_per_scan=10000, seed=3, odometry_tilt_noise_deg=NOISE_DEG
    )
    simulate_session(folder, config)
    return folder


def registered_session(root: Path, scans: Path, name: str = "campus") -> Session:
    """A session over ``scans`` whose current revision holds the true poses: a registration that
    kept every scan's tilt, which relaxing again should not undo."""
    session = Session.create(root / name, "Campus", scans)
    session.load_sequence()  # revision 0: the odometry, i.e. the readings
    truth = [UOS.pose_to_canonical(p) for p in read_kitti_poses(scans / "ground_truth_kitti.txt")]
    session.journal.commit(truth, "test", "register", {})
    return session


def relax_cli(session: Path, out: Path, *extra: str) -> list[Matrix]:
    result = CliRunner().invoke(cli, ["relax", str(session), "--out", str(out), *extra])
    assert result.exit_code == 0, result.output
    return read_kitti_poses(out)


def off_readings(poses: list[Matrix], readings: list[Matrix]) -> np.ndarray:
    return np.array([tilt_error_deg(p, measured_up(r)) for p, r in zip(poses, readings, strict=True)])


def test_slam6d_relax_holds_each_scans_tilt_to_the_declared_readings(campus: Path, tmp_path: Path) -> None:
    """With the session's declaration every scan registered against fused scans (all but the first
    two, which ``slam6d run`` weighs as scans finding their planes alone: 0.006° a step) keeps its
    tilt within the declared noise of its reading; with ``--tilt-noise-deg 0`` the scans go where
    the pairs put them, several times farther from the readings (0.08° RMS against 0.02°, up to
    0.17°). Neither bends the map off the truth: LUM pairs against the registration models, whose
    per-cube normals leave a VLP-16's rings no relative tilt to pull by (0.09° at most; against the
    k-NN normals of the reduced scans, 0.2°)."""
    session = registered_session(tmp_path, campus)
    assert session.config.engine["tilt_noise_deg"] == NOISE_DEG
    readings = session.poses(0)
    truth = session.poses()
    held = relax_cli(session.folder, tmp_path / "held.txt")
    free = relax_cli(session.folder, tmp_path / "free.txt", "--tilt-noise-deg", "0")

    held_off, free_off = off_readings(held, readings)[2:], off_readings(free, readings)[2:]
    assert held_off.max() < 1.5 * NOISE_DEG, held_off
    assert np.sqrt(np.mean(held_off**2)) < 0.5 * np.sqrt(np.mean(free_off**2)), (held_off, free_off)
    assert free_off.max() > 2 * NOISE_DEG, free_off
    for relaxed in (held, free):
        assert off_readings(relaxed, truth).max() < 3 * NOISE_DEG


def test_relaxing_without_a_declaration_holds_no_tilt(campus: Path, tmp_path: Path) -> None:
    """A session that declares no inclinometer, and a declared one with ``--tilt-noise-deg 0``, relax
    to exactly the poses the session's relaxation gives without a prior, and the journal says no
    tilt was held; the models the caller handed over keep their own normals (LUM's pairing against
    the registration models is on a copy)."""
    corridor = corridor_session(tmp_path / "sessions", scans=4, points=3000, odometry_noise=0.1)
    for folder, extra in ((corridor, ()), (registered_session(tmp_path, campus).folder, ("--tilt-noise-deg", "0"))):
        session = Session.open(folder)
        sequence = session.load_sequence()
        revision = session.get_revision()  # what the command relaxes
        assert relax_cli(folder, tmp_path / "out.txt", "--commit", *extra)
        relaxed = Session.open(folder).poses()
        config = pipeline_config(session.config.engine)
        models = reduced_models([s.points for s in sequence.scans], config.voxel_size, config.icp)
        without = relax_revision("lum", models, revision, [0], config, tilt=None)
        for a, b in zip(relaxed, without.poses, strict=True):
            np.testing.assert_allclose(a, b, atol=1e-9)
        assert Session.open(folder).journal.entries()[-1].parameters["tilt_noise_deg"] is None
        assert all(models.plane_model(k) is models.index(k) for k in range(len(models)))


def ate(poses: list[Matrix], truth: list[Matrix]) -> float:
    return absolute_trajectory_error(np.array(poses), np.array(truth)).rmse


def test_relaxing_a_runs_poses_again_keeps_its_map(campus: Path, tmp_path: Path) -> None:
    """``slam6d relax`` on the poses ``slam6d run`` registered pairs LUM as the run's relaxation did
    (the scans' registration models), so relaxing again leaves the map about as good as it was:
    the ATE grows by no more than 3 mm, with the readings held and without. Paired against the
    reduced scans' k-NN normals instead, a VLP-16's rings pulled the 20 campus scans from 0.70 cm to
    1.29 cm (2.91 cm without the readings) and the 250-scan campus from 3.5 to 15.6 cm."""
    out = tmp_path / "run"
    ran = CliRunner().invoke(cli, ["run", str(campus), "--format", "uos", "--out", str(out)])
    assert ran.exit_code == 0, ran.output
    registered = [UOS.pose_to_canonical(p) for p in read_kitti_poses(out / "poses_kitti.txt")]
    session = Session.create(tmp_path / "session", "Campus", campus)
    session.load_sequence()  # revision 0: the odometry, i.e. the readings
    session.journal.commit(registered, "test", "register", {"from": "slam6d run"})
    truth = [UOS.pose_to_canonical(p) for p in read_kitti_poses(campus / "ground_truth_kitti.txt")]
    before = ate(registered, truth)
    held = ate(relax_cli(session.folder, tmp_path / "held.txt"), truth)
    free = ate(relax_cli(session.folder, tmp_path / "free.txt", "--tilt-noise-deg", "0"), truth)
    assert before < 0.02, before  # a run worth keeping
    assert held <= before + 0.003, (before, held)
    assert free <= before + 0.003, (before, free)


def test_the_workbench_relax_job_holds_the_sessions_declared_tilt(campus: Path, tmp_path: Path) -> None:
    """The Relax job passes the session's ``[engine] tilt_noise_deg`` and readings to the engine: it
    relaxes to the poses ``slam6d relax`` gives with the declaration, not without it, and its journal
    entry names the noise held."""
    root = tmp_path / "sessions"
    registered_session(root, campus)
    copy = tmp_path / "copy"
    shutil.copytree(root / "campus", copy)
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as client:
        response = client.post("/api/sessions/campus/relax", json={"method": "lum", "fixed": [0]})
        assert response.status_code == 202, response.text
        job = client.app.state.workbench.jobs.wait(response.json()["id"], timeout=300)  # type: ignore[attr-defined]
        assert job.status == "done", job.message
        from_workbench = client.app.state.workbench.current_poses("campus")  # type: ignore[attr-defined]
    (entry,) = [e for e in Session.open(root / "campus").journal.entries() if e.kind == "relax_lum"]
    assert entry.parameters["tilt_noise_deg"] == NOISE_DEG

    held = relax_cli(copy, tmp_path / "held.txt")
    free = relax_cli(copy, tmp_path / "free.txt", "--tilt-noise-deg", "0")
    for a, b in zip(from_workbench[1:], held[1:], strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)
    assert max(np.abs(a - b).max() for a, b in zip(from_workbench, free, strict=True)) > 1e-3


def test_the_prior_without_readings_is_refused_naming_where_they_would_be(tmp_path: Path) -> None:
    """Asked for where no scan carried odometry, the prior is an error naming session.toml's
    sources (not a relaxation quietly run without it); ``simultaneous`` and a negative noise are
    refused as options."""
    small = {"scans": 3, "points_per_scan": 3000, "loop_length": 16.0, "loop_width": 10.0, "odometry": False}
    simulate_session(tmp_path / "blind", SimulationConfig(**small))  # type: ignore[arg-type]
    folder = Session.create(tmp_path / "session", "Blind", tmp_path / "blind").folder
    refused = CliRunner().invoke(cli, ["relax", str(folder), "--tilt-noise-deg", "0.3"])
    assert isinstance(refused.exception, SessionError)
    assert "session.toml" in str(refused.exception) and "[source] paths" in str(refused.exception)
    simultaneous = CliRunner().invoke(cli, ["relax", str(folder), "--method", "simultaneous", "--tilt-noise-deg", "1"])
    assert simultaneous.exit_code == 2 and "simultaneous" in simultaneous.output
    negative = CliRunner().invoke(cli, ["relax", str(folder), "--tilt-noise-deg", "-1"])
    assert negative.exit_code == 2 and "--tilt-noise-deg" in negative.output


def test_closing_a_loop_on_a_revision_keeps_the_tilt_where_readings_are_held() -> None:
    """A loop whose verified transform is 1° off in pitch (a registration's relative tilt) tilts
    every scan after it by that much when closed plainly; with the readings held its correction
    turns about "up" only: every scan keeps its tilt, and the loop's end still lands where the loop
    puts it."""
    poses = [pose_from_xyzrpy(3.0 * k, 0.2 * k, 0.0, 0.0, 0.0, math.radians(2.0 * k)) for k in range(8)]
    said = invert(poses[0]) @ poses[5] @ pose_from_xyzrpy(0.3, -0.2, 0.05, 0.0, math.radians(1.0), math.radians(3.0))
    loop = LoopHypothesis(0, 5, 0.0, 0.0, transform=said)
    plain = close_revision_loops(poses, [loop], keep_tilt=False)
    kept = close_revision_loops(poses, [loop], keep_tilt=True)
    tilt = [tilt_error_deg(after, measured_up(before)) for before, after in zip(poses, plain, strict=True)]
    assert max(tilt[5:]) == pytest.approx(1.0, abs=0.05)
    for before, after in zip(poses, kept, strict=True):
        assert tilt_error_deg(after, measured_up(before)) < 1e-6
    np.testing.assert_allclose(kept[5][:3, 3], plain[5][:3, 3], atol=1e-9)
    assert np.linalg.norm(kept[5][:3, 3] - poses[5][:3, 3]) > 0.3  # it did close the loop


def test_the_workbench_close_loops_job_keeps_the_tilt_of_a_declared_session(campus: Path, tmp_path: Path) -> None:
    """The Close loops job hands the session's declaration to the engine: a session holding an
    inclinometer closes its loop edges keeping every scan's tilt, and its journal entry says so."""
    root = tmp_path / "sessions"
    before = registered_session(root, campus).poses()
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as client:
        assert client.post("/api/sessions/campus/edges", json={"i": 0, "j": 3, "force": True}).status_code == 201
        response = client.post("/api/sessions/campus/close-loops", json={})
        assert response.status_code == 202, response.text
        job = client.app.state.workbench.jobs.wait(response.json()["id"], timeout=300)  # type: ignore[attr-defined]
        assert job.status == "done", job.message
        after = client.app.state.workbench.current_poses("campus")  # type: ignore[attr-defined]
    (entry,) = [e for e in Session.open(root / "campus").journal.entries() if e.kind == "close_loops"]
    assert entry.parameters["tilt_kept"] is True
    assert max(np.abs(a - b).max() for a, b in zip(before, after, strict=True)) > 1e-6  # it moved scans
    for a, b in zip(before, after, strict=True):  # to the rounding of a stored revision
        assert tilt_error_deg(b, measured_up(a)) < 1e-3


def test_a_workbench_run_from_a_later_revision_holds_revision_0s_readings(campus: Path, tmp_path: Path) -> None:
    """A registration job starts from the session's head; the inclinometer's readings stay those of
    revision 0. With a head whose every scan after the first is tilted 1° (an earlier estimate gone
    wrong), the run holds the scans to the odometry's readings, not to that tilt."""
    root = tmp_path / "sessions"
    session = registered_session(root, campus)
    truth = session.poses()
    tilted = [truth[0]] + [p @ pose_from_xyzrpy(0.0, 0.0, 0.0, math.radians(1.0), 0.0, 0.0) for p in truth[1:]]
    session.journal.commit(tilted, "test", "manual_move", {})
    parameters = {"loops": False, "relaxation": "none"}
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as client:
        response = client.post("/api/sessions/campus/jobs", json={"kind": "register", "parameters": parameters})
        assert response.status_code == 202, response.text
        job = client.app.state.workbench.jobs.wait(response.json()["id"], timeout=600)  # type: ignore[attr-defined]
        assert job.status == "done", job.message
        registered = client.app.state.workbench.current_poses("campus")  # type: ignore[attr-defined]
    off_truth = off_readings(registered, truth)[2:]
    off_head = off_readings(registered, tilted)[2:]
    assert np.sqrt(np.mean(off_truth**2)) < 0.25, off_truth
    assert off_head.min() > 0.75, off_head
