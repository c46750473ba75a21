"""Opened sessions are held under a memory budget: idle ones release their scans, and read them again
when next needed, without the user seeing anything but the time it takes."""

from __future__ import annotations

import shutil
import threading

import pytest
from fastapi.testclient import TestClient

from app.editing import editor_for
from app.resources import ResourceLimits
from app.server import create_app
from tests.session_fixtures import corridor_session


@pytest.fixture
def sessions(tmp_path):
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=500, engine={"voxel_size": 0.2})
    shutil.copytree(root / "corridor", root / "second")
    return root


def budget_app(root, budget: int):  # type: ignore[no-untyped-def]
    return create_app(root, viewers=False, limits=ResourceLimits(session_memory_bytes=budget))


def loaded(client: TestClient) -> dict[str, bool]:
    workbench = client.app.state.workbench  # type: ignore[attr-defined]
    return {sid: workbench.state(sid).loaded for sid in ("corridor", "second")}


def test_a_tiny_budget_keeps_only_the_session_in_use_and_reopens_the_others_transparently(sessions):
    with TestClient(budget_app(sessions, 1), base_url="http://127.0.0.1") as client:
        workbench = client.app.state.workbench  # type: ignore[attr-defined]
        context = editor_for(workbench).context
        first = client.get("/api/sessions/corridor/residuals").json()
        assert loaded(client) == {"corridor": True, "second": False}
        assert "corridor" in context._models
        client.get("/api/sessions/second/residuals").raise_for_status()
        assert loaded(client) == {"corridor": False, "second": True}  # the least recently used went
        assert "corridor" not in context._models and workbench.memory.released == 1
        again = client.get("/api/sessions/corridor/residuals").json()  # read again on demand
        assert again == first
        assert loaded(client) == {"corridor": True, "second": False}
        assert workbench.memory.released == 2


def test_a_large_budget_keeps_every_session(sessions):
    with TestClient(budget_app(sessions, 1 << 30), base_url="http://127.0.0.1") as client:
        for sid in ("corridor", "second", "corridor"):
            client.get(f"/api/sessions/{sid}/residuals").raise_for_status()
        assert loaded(client) == {"corridor": True, "second": True}
        assert client.app.state.workbench.memory.released == 0  # type: ignore[attr-defined]


def test_a_session_with_a_job_is_never_released(sessions):
    with TestClient(budget_app(sessions, 1), base_url="http://127.0.0.1") as client:
        workbench = client.app.state.workbench  # type: ignore[attr-defined]
        release, holding = threading.Event(), threading.Event()

        def work(progress, cancel):  # type: ignore[no-untyped-def]
            workbench.state("corridor").sequence()
            holding.set()
            release.wait(30)
            return {}

        job = workbench.jobs.submit("corridor", "relax", work)
        assert holding.wait(30)
        client.get("/api/sessions/second/residuals").raise_for_status()
        assert loaded(client) == {"corridor": True, "second": True}  # over budget, but the job needs it
        release.set()
        assert workbench.jobs.wait(job.id, 10).status == "done"
        # the job's end lets the budget act: the least recently used idle session goes
        assert loaded(client) == {"corridor": False, "second": True}


def test_memory_budget_must_be_positive():
    with pytest.raises(ValueError, match="session_memory_bytes"):
        ResourceLimits(session_memory_bytes=0)
