"""Permalinks checked on the server, and one name per person (journal, comments, who am I) over REST."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from app.tokens import Role
from slam6d.geometry import make_pose, rot_z
from slam6d.session import Session
from tests.session_fixtures import corridor_session

SESSION = "/api/sessions/corridor"
CAMERA = "1,2,3,4,5,6,0,0,1,50"


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=400, engine={"voxel_size": 0.2})
    session = Session.open(root / "corridor")
    session.load_sequence()
    poses = session.poses()
    poses[1] = poses[1] @ make_pose(rot_z(0.1), [0.5, 0.0, 0.0])
    session.journal.commit(poses, "ana", "manual_move", {"scan": 1})  # revision 1: scan 1 moved
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as c:
        yield c


def test_a_link_is_resolved_against_the_revision_it_names(client: TestClient) -> None:
    head = client.get(SESSION).json()["revision"]
    link = client.get(f"{SESSION}/link", params={"rev": "0", "cam": CAMERA, "sel": "scan:1", "colour": "height"})
    assert link.status_code == 200, link.text
    answer = link.json()
    assert answer["revision"] == 0 and answer["head"] == head and answer["old"] is True
    assert answer["camera"] == {"position": [1, 2, 3], "look_at": [4, 5, 6], "up": [0, 0, 1], "fov_deg": 50}
    assert answer["colour"] == "height"
    old_position = answer["selection"]["position"]
    new_position = client.get(f"{SESSION}/link", params={"sel": "scan:1"}).json()["selection"]["position"]
    assert np.linalg.norm(np.subtract(old_position, new_position)) > 0.4  # the scan as it was at revision 0
    edge = client.get(f"{SESSION}/link", params={"sel": "edge:2-1"}).json()["selection"]
    assert (edge["i"], edge["j"], edge["edge_kind"]) == (1, 2, "sequential")
    assert client.get(f"{SESSION}/link").json()["old"] is False


@pytest.mark.parametrize(
    ("parameter", "value", "expected"),
    [
        ("rev", "x", "rev: must be a revision number"),
        ("rev", "99", "rev: this session has no revision 99"),
        ("cam", "1,2,3", "cam: needs 10 numbers"),
        ("cam", "1,2,3,4,5,6,0,0,1,nan", "cam: numbers must be finite"),
        ("cam", "1,2,3,1,2,3,0,0,1,50", "cam: position and look-at point are the same"),
        ("cam", "1,2,3,4,5,6,0,0,0,50", "cam: the up vector is zero"),
        ("cam", "1,2,3,4,5,6,0,0,1,200", "cam: field of view must be 1-179"),
        ("sel", "scan:x", "sel: must be scan:K"),
        ("sel", "scan:7", "sel: no scan 7"),
        ("sel", "edge:0-2", "sel: revision 1 has no edge 0-2"),
        ("sel", "loop:0-2", "sel: no loop hypothesis 0-2"),
        ("sel", "edge:1-1", "sel: an edge joins two different scans"),
        ("colour", "rainbow", "colour: must be one of scan, height, residual, component"),
    ],
)
def test_bad_link_parameters_are_422_naming_the_parameter_on_rest_and_on_the_page(
    client: TestClient, parameter: str, value: str, expected: str
) -> None:
    for path in (f"{SESSION}/link", "/sessions/corridor"):
        answer = client.get(path, params={parameter: value})
        assert answer.status_code == 422, (path, answer.text)
        assert answer.json()["detail"].startswith(expected), answer.json()
    assert client.get("/sessions/corridor", params={"rev": "0", "cam": CAMERA, "sel": "edge:0-1"}).status_code == 200


def test_one_name_serves_journal_comments_and_who_am_i(client: TestClient) -> None:
    """On an open server the page's name field (header or cookie) is the author everywhere; with a token the
    token's name, whatever the page sends."""
    client.cookies.set("slam6d-author", "B%C3%A9a")  # the page stores it URI-encoded
    assert client.get("/api/me").json()["name"] == "Béa"
    moved = client.post(f"{SESSION}/scans/2/pose", json={"pose": np.eye(4).tolist()})
    assert moved.status_code == 200, moved.text
    comment = client.post(f"{SESSION}/comments", json={"anchor": {"scan": 0}, "text": "look"}).json()
    assert comment["author"] == "Béa"
    revision = moved.json()["revision"]
    entry = next(e for e in client.get(f"{SESSION}/journal").json() if e.get("revision") == revision)
    assert entry["author"] == "Béa"

    secret, _ = client.app.state.tokens.issue(Role.editor, "corridor", name="tok")  # type: ignore[attr-defined]
    headers = {"Authorization": f"Bearer {secret}", "X-Author": "mallory"}
    assert client.get("/api/me", headers=headers).json()["name"] == "tok"
    noted = client.post(f"{SESSION}/comments", json={"anchor": {"scan": 1}, "text": "x"}, headers=headers)
    assert noted.json()["author"] == "tok"
