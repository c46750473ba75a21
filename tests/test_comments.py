"""Comments anchored to a scan point (moving with the scan), an edge or a loop; resolved; by role."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from app.tokens import Role
from tests.session_fixtures import corridor_session

API = "/api/sessions/corridor"


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    corridor_session(tmp_path / "sessions", scans=4, points=1200, odometry_noise=0.05, engine={"voxel_size": 0.15})
    app = create_app(tmp_path / "sessions", viewers=False, require_token=True)
    with TestClient(app, base_url="http://127.0.0.1") as c:
        yield c


def token(client: TestClient, role: Role, name: str) -> dict[str, str]:
    secret, _ = client.app.state.tokens.issue(role, "corridor", name=name)  # type: ignore[attr-defined]
    return {"Authorization": f"Bearer {secret}"}


def test_a_note_on_a_scan_moves_with_the_scan(client: TestClient) -> None:
    rita, ed = token(client, Role.reviewer, "rita"), token(client, Role.editor, "ed")
    point = [1.0, -0.5, 0.8]  # in scan 2's own frame
    added = client.post(
        f"{API}/comments", json={"anchor": {"scan": 2, "point": point}, "text": "wall doubled"}, headers=rita
    )
    assert added.status_code == 201, added.text
    assert added.json()["author"] == "rita" and added.json()["status"] == "open" and added.json()["id"] == 1
    pose = client.app.state.workbench.current_poses("corridor")[2]  # type: ignore[attr-defined]
    listed = client.get(f"{API}/comments", headers=rita).json()
    assert listed[0]["world"] == pytest.approx((pose @ [*point, 1.0])[:3], abs=1e-9)
    moved = pose.copy()
    moved[:3, 3] += [0.4, 0.2, 0.0]
    assert client.post(f"{API}/scans/2/pose", json={"pose": moved.tolist()}, headers=ed).status_code == 200
    after = client.get(f"{API}/comments", headers=rita).json()[0]["world"]
    assert after == pytest.approx((moved @ [*point, 1.0])[:3], abs=1e-9)
    at_start = client.get(f"{API}/comments?rev=0", headers=rita).json()[0]["world"]
    assert at_start == pytest.approx((pose @ [*point, 1.0])[:3], abs=1e-9)


def test_edge_and_loop_notes_sit_between_their_scans_and_can_be_resolved(client: TestClient) -> None:
    rita = token(client, Role.reviewer, "rita")
    client.post(f"{API}/comments", json={"anchor": {"edge": [0, 1]}, "text": "weak edge"}, headers=rita)
    client.post(f"{API}/comments", json={"anchor": {"loop": [0, 3]}, "text": "is this real?"}, headers=rita)
    poses = client.app.state.workbench.current_poses("corridor")  # type: ignore[attr-defined]
    edge, loop = client.get(f"{API}/comments", headers=rita).json()
    assert edge["world"] == pytest.approx(0.5 * (poses[0][:3, 3] + poses[1][:3, 3]))
    assert loop["world"] == pytest.approx(0.5 * (poses[0][:3, 3] + poses[3][:3, 3]))
    resolved = client.post(f"{API}/comments/{loop['id']}/status", json={"status": "resolved"}, headers=rita)
    assert resolved.status_code == 200 and resolved.json()["status"] == "resolved"
    assert resolved.json()["status_by"] == "rita"
    journal = client.get(f"{API}/journal", headers=rita).json()
    assert [e["kind"] for e in journal].count("comments") == 3  # each change is in the history


def test_bad_anchors_unknown_ids_and_viewers_are_refused(client: TestClient) -> None:
    rita, vic = token(client, Role.reviewer, "rita"), token(client, Role.viewer, "vic")
    both = {"anchor": {"scan": 1, "edge": [0, 1]}, "text": "x"}
    assert client.post(f"{API}/comments", json=both, headers=rita).status_code == 422
    assert client.post(f"{API}/comments", json={"anchor": {}, "text": "x"}, headers=rita).status_code == 422
    far = {"anchor": {"scan": 1, "point": [1e300, 0, 0]}, "text": "x"}
    assert client.post(f"{API}/comments", json=far, headers=rita).status_code == 422
    missing = client.post(f"{API}/comments", json={"anchor": {"scan": 9}, "text": "x"}, headers=rita)
    assert missing.status_code == 404 and "no scan 9" in missing.json()["detail"]
    assert client.post(f"{API}/comments/7/status", json={"status": "resolved"}, headers=rita).status_code == 404
    ok = {"anchor": {"scan": 1}, "text": "fine"}
    assert client.post(f"{API}/comments", json=ok, headers=vic).status_code == 403
    assert client.get(f"{API}/comments", headers=vic).json() == []
    assert client.post(f"{API}/comments", json=ok, headers=rita).status_code == 201
