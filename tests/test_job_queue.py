"""Jobs are bounded per session lane and over the server, and queued beyond the bounds, never refused.

The work functions here block on events the test sets, so which job runs when is decided by the
test, not by timing; the REST tests use the real relaxation and render routes.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.jobs import MAX_QUEUED_PER_SESSION, Job, JobManager, lane_of
from app.resources import ResourceLimits
from app.server import create_app
from slam6d.errors import Cancelled, Slam6dError
from tests.session_fixtures import corridor_session


class Gate:
    """A job's work that says when it started and runs until released (or cancelled)."""

    def __init__(self, fail: bool = False) -> None:
        self.started = threading.Event()
        self.release = threading.Event()
        self.fail = fail

    def __call__(self, progress: Callable[[str, int, int], None], cancel: Callable[[], bool]) -> dict[str, Any]:
        self.started.set()
        while not self.release.wait(0.01):
            if cancel():
                raise Cancelled("stopped")
        if self.fail:
            raise Slam6dError("the engine gave up")
        return {"ok": True}


def until(condition: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.01)


def test_lanes():
    assert lane_of("relax") == lane_of("register") == lane_of("close-loops") == lane_of("detect-loops") == "poses"
    assert lane_of("render") == "render" and lane_of("reload") == "read"


def test_second_relaxation_of_a_session_waits_then_runs():
    jobs = JobManager(max_running=4)
    first, second = Gate(), Gate()
    a = jobs.submit("s", "relax", first)
    b = jobs.submit("s", "relax", second)
    assert first.started.wait(5)
    assert b.status == "queued" and b.as_dict()["position"] == 1 and not second.started.is_set()
    first.release.set()
    assert jobs.wait(a.id, 5).status == "done"
    assert second.started.wait(5)  # its slot came free
    assert b.status == "running" and b.as_dict()["position"] is None
    second.release.set()
    assert jobs.wait(b.id, 5).status == "done"


def test_a_render_and_a_relaxation_run_together_and_other_sessions_are_not_held_up():
    jobs = JobManager(max_running=4)
    relax, render, other = Gate(), Gate(), Gate()
    started = [jobs.submit("s", "relax", relax), jobs.submit("s", "render", render), jobs.submit("t", "relax", other)]
    for gate in (relax, render, other):
        assert gate.started.wait(5)
    assert [j.status for j in started] == ["running"] * 3
    for gate in (relax, render, other):
        gate.release.set()
    assert [jobs.wait(j.id, 5).status for j in started] == ["done"] * 3


def test_the_global_limit_holds_and_the_queue_runs_in_order():
    jobs = JobManager(max_running=2)
    gates = [Gate() for _ in range(5)]
    submitted = [jobs.submit(f"session-{k}", "relax", gate) for k, gate in enumerate(gates)]
    assert gates[0].started.wait(5) and gates[1].started.wait(5)
    assert [j.status for j in submitted] == ["running", "running", "queued", "queued", "queued"]
    assert [j.position for j in submitted[2:]] == [1, 2, 3]
    for k in range(5):
        gates[k].release.set()
        assert jobs.wait(submitted[k].id, 5).status == "done"
        running = [j for j in submitted if j.status == "running"]
        assert len(running) <= 2
        if k + 2 < 5:  # the next in line took the freed slot
            assert gates[k + 2].started.wait(5)
    assert not any(j.active for j in submitted)


def test_a_failed_or_cancelled_job_frees_its_slot():
    jobs = JobManager(max_running=1)
    failing, cancelled, last = Gate(fail=True), Gate(), Gate()
    a = jobs.submit("s", "relax", failing)
    b = jobs.submit("t", "render", cancelled)
    c = jobs.submit("u", "reload", last)
    failing.release.set()
    assert jobs.wait(a.id, 5).status == "failed" and a.message == "the engine gave up"
    assert cancelled.started.wait(5)
    jobs.cancel(b.id)
    assert jobs.wait(b.id, 5).status == "cancelled"
    assert last.started.wait(5)
    last.release.set()
    assert jobs.wait(c.id, 5).status == "done"


def test_cancelling_a_queued_job_ends_it_at_once_and_it_never_runs():
    records: list[tuple[str, str, str]] = []
    jobs = JobManager(record=lambda job, event: records.append((job.id, event, job.status)), max_running=1)
    running, waiting, behind = Gate(), Gate(), Gate()
    a = jobs.submit("s", "relax", running)
    b = jobs.submit("s", "relax", waiting)
    c = jobs.submit("s", "relax", behind)
    assert (b.position, c.position) == (1, 2)
    jobs.cancel(b.id)
    assert b.status == "cancelled" and b.finished is not None and jobs.wait(b.id, 1) is b
    assert c.position == 1  # moved up
    running.release.set()
    assert behind.started.wait(5) and not waiting.started.is_set()
    behind.release.set()
    assert jobs.wait(c.id, 5).status == "done"
    # journaled: accepted, and for the one that waited, when it really began
    assert (b.id, "finished", "cancelled") in records
    assert [e for i, e, _ in records if i == c.id] == ["started", "running", "finished"]
    assert [e for i, e, _ in records if i == a.id] == ["started", "finished"]


def test_a_session_queue_is_bounded():
    jobs = JobManager(max_running=1)
    gate = Gate()
    jobs.submit("s", "relax", gate)
    queued = [jobs.submit("s", "relax", Gate()) for _ in range(MAX_QUEUED_PER_SESSION)]
    with pytest.raises(Slam6dError, match="jobs queued"):
        jobs.submit("s", "relax", Gate())
    jobs.submit("t", "relax", Gate())  # another session still may queue
    for job in queued:
        jobs.cancel(job.id)
    gate.release.set()


# -------------------------------------------------------------- over REST


@pytest.fixture
def client(tmp_path):
    root = tmp_path / "sessions"
    corridor_session(root, scans=4, points=600, engine={"voxel_size": 0.2})
    app = create_app(root, viewers=False, limits=ResourceLimits(max_jobs=2))
    with TestClient(app, base_url="http://127.0.0.1") as c:
        yield c


def hold_poses_lane(client: TestClient) -> tuple[Job, Gate]:
    """A job of the session's poses lane that runs until the test releases it."""
    gate = Gate()
    job = client.app.state.workbench.jobs.submit("corridor", "relax", gate)  # type: ignore[attr-defined]
    assert gate.started.wait(5)
    return job, gate


def test_rest_a_relaxation_behind_another_is_queued_then_runs_and_shows_its_place(client):
    holder, gate = hold_poses_lane(client)
    answer = client.post("/api/sessions/corridor/relax", json={})
    assert answer.status_code == 202
    queued = answer.json()
    assert queued["status"] == "queued" and queued["position"] == 1 and queued["lane"] == "poses"
    assert client.get(f"/api/jobs/{queued['id']}").json()["status"] == "queued"
    listed = {j["id"]: j for j in client.get("/api/sessions/corridor").json()["jobs"]}
    assert listed[queued["id"]]["status"] == "queued" and listed[holder.id]["status"] == "running"
    gate.release.set()
    job = client.app.state.workbench.jobs.wait(queued["id"], 120)  # type: ignore[attr-defined]
    assert job.status == "done", job.message
    assert client.get("/api/sessions/corridor").json()["revision"] == 1  # the relaxation committed


def test_rest_a_render_runs_beside_a_relaxation(client):
    _, gate = hold_poses_lane(client)
    answer = client.post("/api/sessions/corridor/render", json={"width": 32, "height": 24, "frames": 2})
    assert answer.status_code == 202
    job = client.app.state.workbench.jobs.wait(answer.json()["id"], 120)  # type: ignore[attr-defined]
    assert job.status == "done", job.message  # finished while the relaxation still held its lane
    gate.release.set()


def test_rest_cancel_a_queued_job(client):
    _, gate = hold_poses_lane(client)
    queued = client.post("/api/sessions/corridor/jobs", json={"kind": "register"}).json()
    assert queued["status"] == "queued"
    cancelled = client.delete(f"/api/jobs/{queued['id']}").json()
    assert cancelled["status"] == "cancelled" and cancelled["position"] is None
    assert client.get(f"/api/jobs/{queued['id']}").json()["status"] == "cancelled"
    gate.release.set()
    entries = client.get("/api/sessions/corridor/journal").json()
    ends = [e["parameters"] for e in entries if e["kind"] == "job" and e["parameters"]["id"] == queued["id"]]
    assert ends[-1]["event"] == "finished" and ends[-1]["status"] == "cancelled"


def test_the_server_command_takes_the_limits_and_refuses_nonsense(tmp_path, capsys):
    from app.main import main, serve_parser

    args = serve_parser().parse_args(
        ["--max-jobs", "3", "--session-memory-budget", "0.5", "--viewer-grace", "5", "--parse-timeout", "20"]
    )
    assert (args.max_jobs, args.session_memory_budget, args.viewer_grace, args.parse_timeout) == (3, 0.5, 5.0, 20.0)
    with pytest.raises(SystemExit) as stopped:
        main(["--sessions-dir", str(tmp_path), "--max-jobs", "0"])
    assert stopped.value.code == 2 and "--max-jobs must be positive" in capsys.readouterr().err
