"""Repair on start: a killed server or an older version's data never wedges a session, and a session
that cannot be trusted is refused with the reason while the others open."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from app.server import create_app
from slam6d.repair import JOB_ENTRY, check_session
from slam6d.session import JOURNAL_FILE, Session
from tests.session_fixtures import corridor_session

BAD_KEYFRAME = {"position": [0, 0, 1], "orientation_wxyz": [0, 0, 0, 0], "fov_deg": 60}
GOOD_KEYFRAME = {"position": [0.0, 0.0, 1.0], "orientation_wxyz": [1.0, 0.0, 0.0, 0.0], "fov_deg": 60.0}


def _damaged(root: Path) -> Session:
    """A session as an older version or a crash could leave it: a sheared head pose stored without
    checks, a keyframe with a zero quaternion, a job that started and never ended."""
    session = Session.open(corridor_session(root, scans=3, points=300))
    session.load_sequence()
    poses = session.poses()
    sheared = poses[1].copy()
    sheared[0, 1] += 0.3
    with sqlite3.connect(session.journal.path) as conn:  # what the journal refuses today, written by hand
        conn.execute(
            "INSERT INTO entries (time, author, kind, parameters, head, revision) VALUES ('t','old','move','{}',1,1)"
        )
        entry = conn.execute("SELECT MAX(id) FROM entries").fetchone()[0]
        stack = np.stack([poses[0], sheared, poses[2]])
        conn.execute(
            "INSERT INTO revisions VALUES (1, 0, ?, 3, ?, '{}')",
            (entry, stack.tobytes()),
        )
    session.journal.append("old", "camera_path", {"keyframes": [GOOD_KEYFRAME, BAD_KEYFRAME]})
    session.journal.append("ana", JOB_ENTRY, {"id": "job-lost", "event": "started", "kind": "relax", "revision": 1})
    return session


def test_check_session_repairs_head_camera_path_and_marks_interrupted_jobs(tmp_path: Path) -> None:
    session = _damaged(tmp_path)
    check = check_session(session.folder)
    assert check.error is None
    assert len(check.repaired) == 3, check.repaired
    assert "revision 1: 1 pose(s) not rigid" in check.repaired[0]
    assert check.repaired[1].startswith("camera path: 1 keyframe(s)")
    assert "job job-lost (relax) was interrupted; it had started from revision 1" in check.repaired[2]
    head = session.get_revision()
    assert head.number == 2 and head.parent == 1
    rotation = head.poses[1][:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
    assert session.camera_path() == [GOOD_KEYFRAME]
    assert check_session(session.folder).repaired == []  # nothing left to repair the second time


def test_the_server_starts_with_a_broken_session_and_answers_for_lost_jobs(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    _damaged(root)
    broken = root / "broken"
    broken.mkdir()
    (root / "corridor" / "session.toml").replace(broken / "session.toml")
    (root / "corridor" / "session.toml").write_text((broken / "session.toml").read_text())
    (broken / JOURNAL_FILE).write_bytes(b"SQLite format 3\x00" + b"\x13" * 4000)  # garbage pages
    with TestClient(
        create_app(root, viewers=False), base_url="http://127.0.0.1", raise_server_exceptions=False
    ) as client:
        listed = {s["id"]: s for s in client.get("/api/sessions").json()}
        assert listed["broken"]["error"] and "cannot be opened" in listed["broken"]["error"]
        assert listed["corridor"]["error"] is None and len(listed["corridor"]["repaired"]) == 3
        assert client.get("/api/sessions/broken").status_code == 422
        assert client.get("/api/sessions/corridor/poses").status_code == 200
        lost = client.get("/api/jobs/job-lost")
        assert lost.status_code == 200, lost.text
        assert lost.json()["status"] == "interrupted" and lost.json()["revision"] == 1
        assert client.get("/api/jobs/job-never").status_code == 404


def test_jobs_are_journaled_when_they_start_and_end(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=300)
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as client:
        job = client.post("/api/sessions/corridor/jobs", json={"kind": "reload", "parameters": {}}).json()
        client.app.state.workbench.jobs.wait(job["id"])  # type: ignore[attr-defined]
        records = [e for e in Session.open(root / "corridor").journal.entries() if e.kind == JOB_ENTRY]
        assert [r.parameters["event"] for r in records] == ["started", "finished"]
        assert records[1].parameters["status"] == "done" and records[0].parameters["id"] == job["id"]
