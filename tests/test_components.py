"""The pieces a relaxation would see: a session whose graph is cut shows its components over REST, an
edge added between two scans of different components bridges them, and relaxing then succeeds."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from tests.session_fixtures import corridor_session

CORRIDOR = "/api/sessions/corridor"


@pytest.fixture
def client(tmp_path):  # type: ignore[no-untyped-def]
    root = tmp_path / "sessions"
    corridor_session(root, scans=6, points=3000, odometry_noise=0.05, engine={"voxel_size": 0.1})
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as client:
        yield client


def relax(client: TestClient, method: str):  # type: ignore[no-untyped-def]
    response = client.post(f"{CORRIDOR}/relax", json={"method": method, "fixed": [0]})
    assert response.status_code == 202, response.text
    return client.app.state.workbench.jobs.wait(response.json()["id"], timeout=120)  # type: ignore[attr-defined]


def test_a_cut_graph_shows_its_components_and_an_added_edge_bridges_them(client) -> None:  # type: ignore[no-untyped-def]
    whole = client.get(f"{CORRIDOR}/components", params={"method": "graph"}).json()
    assert whole["components"] == [[0, 1, 2, 3, 4, 5]] and whole["failure"] is None

    # the sequential edge 2-3 deleted: the session's graph falls into two pieces
    assert client.request("DELETE", f"{CORRIDOR}/edges/2", json={}).status_code == 200
    cut = client.get(f"{CORRIDOR}/components", params={"method": "graph"}).json()
    assert cut["count"] == 2 and cut["components"] == [[0, 1, 2], [3, 4, 5]]
    assert cut["ranges"] == "[0-2]; [3-5]" and "disconnected: 2 components [0-2]; [3-5]" in cut["message"]
    assert cut["revision"] == 1
    # graph relaxation refuses it up front, naming the pieces
    refused = client.post(f"{CORRIDOR}/relax", json={"method": "graph", "fixed": [0]})
    assert refused.status_code == 409 and "[0-2]; [3-5]" in refused.text
    # lum finds the scans overlapping, and the consecutive pairs linked except the removed one
    assert client.get(f"{CORRIDOR}/components", params={"method": "lum"}).json()["count"] == 1

    # an ICP-refined edge between a scan of each piece bridges them
    added = client.post(f"{CORRIDOR}/edges", json={"i": 1, "j": 4})
    assert added.status_code == 201, added.text
    bridged = client.get(f"{CORRIDOR}/components", params={"method": "graph"}).json()
    assert bridged["components"] == [[0, 1, 2, 3, 4, 5]] and bridged["revision"] == 2
    job = relax(client, "graph")
    assert job.status == "done", job.message
    after = client.get(f"{CORRIDOR}/components", params={"method": "graph"}).json()
    assert after["count"] == 1 and after["revision"] == 3 and "one connected component" in after["message"]


def test_components_are_read_by_viewers_and_the_method_is_checked(client) -> None:  # type: ignore[no-untyped-def]
    assert client.get(f"{CORRIDOR}/components", params={"method": "sideways"}).status_code == 422
    assert client.get("/api/sessions/nowhere/components").status_code == 404
