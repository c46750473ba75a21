"""The session's head pushed to its pages (``/api/sessions/{id}/events``): guarded, bounded, prompt."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse
from starlette.websockets import WebSocketDisconnect

from app.revision_events import Listener, RevisionEvents
from app.server import create_app
from app.tokens import Role
from slam6d.session import Session
from tests.session_fixtures import corridor_session, write_corridor_scans

SESSION = "corridor"
API = f"/api/sessions/{SESSION}"
EVENTS = f"{API}/events"
ORIGIN = "http://testserver"  # the test client's websockets name this host (whatever its base_url)


@pytest.fixture
def sessions_dir(tmp_path: Path) -> Path:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=1500, odometry_noise=0.1, engine={"voxel_size": 0.1})
    write_corridor_scans(root / "other" / "scans", scans=2, points=500)
    Session.create(root / "other", "Other", "scans")
    return root


@pytest.fixture
def open_server(sessions_dir: Path) -> Iterator[TestClient]:
    with TestClient(create_app(sessions_dir, viewers=False, names=("testserver",)), base_url=ORIGIN) as client:
        yield client


@pytest.fixture
def shared(sessions_dir: Path) -> Iterator[TestClient]:
    app = create_app(sessions_dir, viewers=False, require_token=True, names=("testserver",))
    with TestClient(app, base_url=ORIGIN) as client:
        yield client


def bearer(client: TestClient, role: Role, session: str | None = SESSION, name: str = "") -> dict[str, str]:
    secret, _ = client.app.state.tokens.issue(role, session, name=name or role.name)  # type: ignore[attr-defined]
    return {"Authorization": f"Bearer {secret}"}


def move_scan(client: TestClient, k: int, headers: dict[str, str]) -> int:
    pose = client.app.state.workbench.current_poses(SESSION)[k].copy()  # type: ignore[attr-defined]
    pose[0, 3] += 0.05
    moved = client.post(f"{API}/scans/{k}/pose", json={"pose": pose.tolist()}, headers=headers)
    assert moved.status_code == 200, moved.text
    return int(moved.json()["revision"])


def test_a_page_hears_of_each_new_revision_and_who_made_it(open_server: TestClient) -> None:
    with open_server.websocket_connect(EVENTS, headers={"Origin": ORIGIN}) as events:
        first = events.receive_json()
        assert first["type"] == "revision" and first["revision"] == 0
        assert (first["can_undo"], first["can_redo"]) == (False, False)
        revision = move_scan(open_server, 1, {"X-Author": "UTF-8''%E5%BC%A0%E4%BC%9F"})
        moved = events.receive_json()
        assert (moved["revision"], moved["author"], moved["kind"]) == (revision, "张伟", "manual_move")
        assert moved["entry"] > first["entry"] and moved["can_undo"] and not moved["can_redo"]
        undone = open_server.post(f"{API}/undo", json={"revision": revision}, headers={"X-Author": "bob"})
        assert undone.status_code == 200, undone.text
        event = events.receive_json()
        assert (event["revision"], event["author"], event["kind"]) == (0, "bob", "undo")
        assert event["can_redo"] and not event["can_undo"]
        # what the page is told is what the next undo/redo may name: the redo applies
        redone = open_server.post(f"{API}/redo", json={"revision": event["revision"]}, headers={"X-Author": "bob"})
        assert redone.json() == {"revision": revision}
        assert events.receive_json()["revision"] == revision
    assert open_server.app.state.revision_events.listening(SESSION) == 0  # type: ignore[attr-defined]


def test_without_a_token_the_stream_is_refused_401(shared: TestClient) -> None:
    with pytest.raises(WebSocketDenialResponse) as refused, shared.websocket_connect(EVENTS):
        pass
    assert refused.value.status_code == 401


def test_a_viewer_may_listen_but_not_on_another_session_nor_from_another_site(shared: TestClient) -> None:
    viewer = bearer(shared, Role.viewer, name="vic")
    with shared.websocket_connect(EVENTS, headers={**viewer, "Origin": ORIGIN}) as events:
        assert events.receive_json()["type"] == "revision"
        move_scan(shared, 2, bearer(shared, Role.editor, name="ed"))
        event = events.receive_json()
        assert (event["revision"], event["author"]) == (1, "ed")
    # a token of one session is no token for another: 403 (the route refuses, code 1008)
    with (
        pytest.raises(WebSocketDisconnect) as other,
        shared.websocket_connect("/api/sessions/other/events", headers=viewer),
    ):
        pass
    assert other.value.code == 1008
    with (
        pytest.raises(WebSocketDenialResponse) as foreign,
        shared.websocket_connect(EVENTS, headers={**viewer, "Origin": "http://evil.example"}),
    ):
        pass
    assert foreign.value.status_code == 403


def test_an_unknown_session_is_refused_and_a_removed_one_closes_the_stream(open_server: TestClient) -> None:
    with pytest.raises(WebSocketDisconnect) as unknown, open_server.websocket_connect("/api/sessions/nope/events"):
        pass
    assert unknown.value.code == 4404
    events_hub: RevisionEvents = open_server.app.state.revision_events  # type: ignore[attr-defined]
    events_hub.heartbeat_s = 0.2
    workbench = open_server.app.state.workbench  # type: ignore[attr-defined]
    with open_server.websocket_connect("/api/sessions/other/events") as events:
        assert events.receive_json()["type"] == "revision"
        assert events.receive_json() == {"type": "heartbeat"}  # quiet: still there
        (workbench.sessions_dir / "other" / "session.toml").unlink()  # the session goes
        while (message := events.receive_json())["type"] == "heartbeat":
            pass
        assert message == {"type": "gone"}
        with pytest.raises(WebSocketDisconnect) as closed:
            events.receive_json()
        assert closed.value.code == 4404


def test_the_number_of_streams_per_token_and_per_session_is_bounded(shared: TestClient) -> None:
    hub: RevisionEvents = shared.app.state.revision_events  # type: ignore[attr-defined]
    hub.max_per_grant, hub.max_per_session = 2, 3
    ann, bob = bearer(shared, Role.viewer, name="ann"), bearer(shared, Role.viewer, name="bob")

    def refused(headers: dict[str, str]) -> int:
        with pytest.raises(WebSocketDisconnect) as closed, shared.websocket_connect(EVENTS, headers=headers):
            pass
        return closed.value.code

    with shared.websocket_connect(EVENTS, headers=ann) as a1, shared.websocket_connect(EVENTS, headers=ann) as a2:
        a1.receive_json(), a2.receive_json()
        assert refused(ann) == 1013  # a third for the same token
        with shared.websocket_connect(EVENTS, headers=bob) as b1:
            b1.receive_json()
            assert refused(bob) == 1013  # the session is full
        assert hub.listening(SESSION) == 2
    assert hub.listening(SESSION) == 0


def test_a_listener_keeps_only_the_newest_head_and_never_goes_back() -> None:
    async def scenario() -> list[Any]:
        listener = Listener(SESSION, "local", asyncio.get_running_loop())
        got = []
        for entry in (3, 5, 4):  # a commit's listener that ran late offers an older head
            listener.offer({"entry": entry, "revision": entry})
        await asyncio.sleep(0)
        event = await listener.next(1.0)
        got.append(event and listener.take(event))
        got.append(await listener.next(0.05))  # nothing more: a heartbeat's turn
        listener.offer({"entry": 5, "revision": 5})  # already sent
        await asyncio.sleep(0)
        event = await listener.next(1.0)
        got.append(event and listener.take(event))
        return got

    assert asyncio.run(scenario()) == [{"entry": 5, "revision": 5}, None, None]
