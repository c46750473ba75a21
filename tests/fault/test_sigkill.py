"""The SIGKILL harness: a real server process killed at random moments during edits and jobs, and
restarted, again and again. After every kill: the journal passes ``PRAGMA integrity_check``, every
edit the server acknowledged is in it (the pose it answered for), the session reopens, and every
acknowledged job is either finished or shown as interrupted with the revision it started from.

Loopback only; bounded in time (``SLAM6D_FAULT_SECONDS``, default 1500 s) with at least
``SLAM6D_FAULT_KILLS`` kills (default 50).
"""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from slam6d.geometry import euler_to_rotation, make_pose
from slam6d.journal import check_journal_file
from slam6d.session import JOURNAL_FILE, Session
from tests.session_fixtures import corridor_session

KILLS = int(os.environ.get("SLAM6D_FAULT_KILLS", "50"))
SECONDS = float(os.environ.get("SLAM6D_FAULT_SECONDS", "1500"))
ROOT = Path(__file__).resolve().parents[2]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _start(sessions: Path) -> tuple[subprocess.Popen[bytes], str]:
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    process = subprocess.Popen(
        [sys.executable, "-m", "tests.fault.serve", str(sessions), str(port)], cwd=ROOT, env=env,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/api/sessions", timeout=2).status_code == 200:
                return process, url
        except httpx.HTTPError:
            time.sleep(0.1)
    process.kill()
    raise AssertionError("the server did not start within 120 s")


class Client(threading.Thread):
    """Edits and jobs until told to stop; remembers what the server acknowledged."""

    def __init__(self, url: str, rng: random.Random) -> None:
        super().__init__(daemon=True)
        self.url, self.rng = url, rng
        self.stop = threading.Event()
        self.edits: list[tuple[int, int, np.ndarray]] = []  # (revision, scan, pose)
        self.jobs: list[str] = []
        self.answered = threading.Event()  # the first request (which loads the scans) came back

    def run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=10) as http:
            while not self.stop.is_set():
                try:
                    if self.rng.random() < 0.15:
                        answer = http.post("/api/sessions/corridor/jobs", json={"kind": "reload", "parameters": {}})
                        if answer.status_code == 202:
                            self.jobs.append(answer.json()["id"])
                        continue
                    scan = self.rng.randint(1, 2)
                    pose = make_pose(euler_to_rotation(0, 0, self.rng.uniform(-0.2, 0.2)), [2.0 * scan, 0.1, 0])
                    answer = http.post(f"/api/sessions/corridor/scans/{scan}/pose", json={"pose": pose.tolist()})
                    if answer.status_code == 200:
                        self.edits.append((answer.json()["revision"], scan, pose))
                    self.answered.set()
                except httpx.HTTPError:
                    return  # the server died under us: what was acknowledged is recorded


@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")
def test_every_acknowledged_edit_survives_sigkill(tmp_path: Path) -> None:
    sessions = tmp_path / "sessions"
    corridor_session(sessions, scans=3, points=300)
    Session.open(sessions / "corridor").load_sequence()  # revision 0 before the first edit
    rng = random.Random(17)
    acknowledged: list[tuple[int, int, np.ndarray]] = []
    jobs: list[str] = []
    began, kills = time.monotonic(), 0
    while kills < KILLS and time.monotonic() - began < SECONDS:
        process, url = _start(sessions)
        if kills:  # what the last kill left: reopened, checked, jobs shown as they ended or as interrupted
            with httpx.Client(base_url=url, timeout=30) as http:
                assert http.get("/api/sessions/corridor").status_code == 200
                for job in jobs:
                    status = http.get(f"/api/jobs/{job}").json()["status"]
                    assert status in ("done", "failed", "cancelled", "interrupted"), (job, status)
        client = Client(url, rng)
        client.start()
        client.answered.wait(timeout=60)  # past the first edit (which loads the scans), then a random moment
        time.sleep(rng.uniform(0.0, 1.5))
        os.kill(process.pid, signal.SIGKILL)
        process.wait(timeout=30)
        client.stop.set()
        client.join(timeout=30)
        kills += 1
        acknowledged += client.edits
        jobs += client.jobs
        assert check_journal_file(sessions / "corridor" / JOURNAL_FILE) == []
        session = Session.open(sessions / "corridor")
        for revision, scan, pose in client.edits:
            stored = session.journal.revision(revision)
            assert stored is not None, f"acknowledged revision {revision} lost after kill {kills}"
            np.testing.assert_allclose(stored.poses[scan], pose, atol=1e-9)
    assert kills >= KILLS, f"only {kills} kills in {SECONDS:.0f} s"
    assert acknowledged, "no edit was acknowledged: the harness did not exercise the server"
    process, url = _start(sessions)  # the last restart marks the last kill's jobs
    try:
        with httpx.Client(base_url=url, timeout=30) as http:
            statuses = [http.get(f"/api/jobs/{job}").json()["status"] for job in jobs]
    finally:
        os.kill(process.pid, signal.SIGKILL)
        process.wait(timeout=30)
    assert all(s in ("done", "failed", "cancelled", "interrupted") for s in statuses), statuses
