"""The pieces a relaxation would see: a session whose graph is cut shows its components over REST, an
edge added between two scans of different components bridges them, and relaxing then succeeds."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from slam6d.geometry import UOS, invert, make_pose, pose_difference, rot_z
from slam6d.io.uos import write_uos_scan
from slam6d.session import Session
from tests.session_fixtures import corridor_session
from tests.simulated_loop import simulated_loop

CORRIDOR = "/api/sessions/corridor"


@pytest.fixture
def client(tmp_path):  # type: ignore[no-untyped-def]
    root = tmp_path / "sessions"
    corridor_session(root, scans=6, points=3000, odometry_noise=0.05, engine={"voxel_size": 0.1})
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as client:
        yield client


def relax_job(client: TestClient, api: str, method: str):  # type: ignore[no-untyped-def]
    response = client.post(f"{api}/relax", json={"method": method, "fixed": [0]})
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
    job = relax_job(client, CORRIDOR, "graph")
    assert job.status == "done", job.message
    after = client.get(f"{CORRIDOR}/components", params={"method": "graph"}).json()
    assert after["count"] == 1 and after["revision"] == 3 and "one connected component" in after["message"]


def test_components_are_read_by_viewers_and_the_method_is_checked(client) -> None:  # type: ignore[no-untyped-def]
    assert client.get(f"{CORRIDOR}/components", params={"method": "sideways"}).status_code == 422
    assert client.get("/api/sessions/nowhere/components").status_code == 404


def test_a_piece_far_off_is_carried_back_by_icp_and_lum_then_relaxes_it_in(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Scans 4-7 of a simulated loop stored 1 km away: lum sees two pieces; scan 4 dragged next to scan 3
    with its piece carried along and matched by ICP from there joins them, and lum relaxes the whole."""
    sim = simulated_loop(scans=8, points=20000, seed=1, loop_length=16.0, loop_width=10.0)
    folder = tmp_path / "sessions" / "apart"
    far = make_pose(np.eye(3), [1000.0, 0.0, 0.0])
    for k, scan in enumerate(sim.sequence.scans):
        pose = sim.truth[k] if k < 4 else far @ sim.truth[k]
        write_uos_scan(folder / "scans", k, UOS.points_to_native(scan.points), UOS.pose_to_native(pose))
    Session.create(folder, "Apart", "scans")
    api = "/api/sessions/apart"
    with TestClient(create_app(tmp_path / "sessions", viewers=False), base_url="http://127.0.0.1") as client:
        pieces = client.get(f"{api}/components").json()
        assert pieces["method"] == "lum" and pieces["components"] == [[0, 1, 2, 3], [4, 5, 6, 7]]
        refused = relax_job(client, api, "lum")
        assert refused.status == "failed" and "disconnected" in refused.message

        # the operator drags scan 4 roughly into place (15 cm, 3 degrees off) and runs ICP from there
        dragged = sim.truth[4] @ make_pose(rot_z(np.radians(3.0)), [0.15, -0.1, 0.0])
        moved = client.post(f"{api}/scans/4/pose", json={"pose": dragged.tolist(), "refine": True, "carry": [5, 6, 7]})
        assert moved.status_code == 200, moved.text
        poses = client.app.state.workbench.current_poses("apart")  # type: ignore[attr-defined]
        start, _ = pose_difference(dragged, sim.truth[4])
        matched, _ = pose_difference(poses[4], sim.truth[4])
        assert start > 0.15 and matched < 0.03, (start, matched)  # ICP from the dragged place, against scan 3
        for k in range(5, 8):  # the piece came along rigidly
            metres, _ = pose_difference(invert(poses[4]) @ poses[k], invert(sim.truth[4]) @ sim.truth[k])
            assert metres < 1e-3, (k, metres)
        journal = client.get(f"{api}/journal").json()[-1]
        assert journal["kind"] == "icp_move" and journal["parameters"]["carry"] == [5, 6, 7]
        assert client.get(f"{api}/components").json()["components"] == [list(range(8))]

        job = relax_job(client, api, "lum")
        assert job.status == "done", job.message
        poses = client.app.state.workbench.current_poses("apart")  # type: ignore[attr-defined]
    errors = [pose_difference(invert(poses[0]) @ poses[k], invert(sim.truth[0]) @ sim.truth[k])[0] for k in range(8)]
    assert max(errors) < 0.05, errors
