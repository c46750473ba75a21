"""Sharing safely over REST: tokens and roles, cross-site and host checks, the data root, If-Match/ETag."""

from __future__ import annotations

import re
import sqlite3
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.main import main, serve_parser
from app.server import create_app
from app.tokens import TOKEN_DB, Role, TokenError, TokenStore, parse_duration
from slam6d.session import Session
from tests.session_fixtures import corridor_session, write_corridor_scans

MUTATING = ("post", "put", "patch", "delete")
SESSION = "corridor"
ORIGIN = "http://127.0.0.1"


@pytest.fixture
def sessions_dir(tmp_path: Path) -> Path:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=1500, odometry_noise=0.1, engine={"voxel_size": 0.1})
    write_corridor_scans(root / "other" / "scans", scans=2, points=500)
    Session.create(root / "other", "Other", "scans")  # a second session, for tokens of one session
    return root


@pytest.fixture
def shared(sessions_dir: Path, tmp_path: Path) -> Iterator[TestClient]:
    """A server that requires tokens (as when bound off loopback), with a data root."""
    (tmp_path / "data").mkdir()
    app = create_app(sessions_dir, viewers=False, require_token=True, data_root=tmp_path / "data")
    with TestClient(app, base_url=ORIGIN) as client:
        yield client


def bearer(client: TestClient, role: Role, session: str | None = None, name: str = "") -> dict[str, str]:
    secret, _ = client.app.state.tokens.issue(role, session, name=name or role.name)  # type: ignore[attr-defined]
    return {"Authorization": f"Bearer {secret}"}


def operations(client: TestClient) -> list[tuple[str, str, str]]:
    """Every state-changing operation the API documents: (method, concrete path, required role)."""
    found = []
    for template, methods in client.app.openapi()["paths"].items():  # type: ignore[attr-defined]
        for method, operation in methods.items():
            if method in MUTATING:
                path = re.sub(r"\{session_id\}", SESSION, template)
                path = re.sub(r"\{[^}]+\}", "0", path)
                found.append((method, path, operation.get("x-role", "editor")))
    return found


# ------------------------------------------------------------------ the token store


def test_tokens_are_stored_hashed_and_expire_or_can_be_revoked(tmp_path: Path) -> None:
    store = TokenStore(tmp_path)
    assert not (tmp_path / TOKEN_DB).exists()  # no token issued, no file
    secret, grant = store.issue(Role.reviewer, "corridor", name="ann")
    assert len(secret) >= 40
    assert store.resolve(secret) == grant
    assert store.resolve(secret + "x") is None
    with sqlite3.connect(tmp_path / TOKEN_DB) as conn:
        stored = " ".join(str(v) for row in conn.execute("SELECT * FROM tokens") for v in row)
    assert secret not in stored
    assert grant.allows(Role.viewer, "corridor") and grant.allows(Role.reviewer, "corridor")
    assert not grant.allows(Role.editor, "corridor") and not grant.allows(Role.viewer, "other")
    assert not grant.allows(Role.viewer, None)  # a session's token is no server-wide token
    store.revoke(grant.id)
    assert store.resolve(secret) is None
    assert [g.revoked for g in store.grants()] == [True]
    expired, _ = store.issue(Role.owner, expires_in=timedelta(seconds=-1))
    assert store.resolve(expired) is None
    with pytest.raises(TokenError, match="no token"):
        store.revoke("nope")


def test_durations_and_roles_are_parsed_with_clear_errors() -> None:
    assert parse_duration("7d") == timedelta(days=7)
    assert parse_duration("12h") == timedelta(hours=12)
    assert parse_duration("never") is None
    with pytest.raises(TokenError, match="'7 days' is not a duration"):
        parse_duration("7 days")
    with pytest.raises(TokenError, match="unknown role 'admin'"):
        Role.parse("admin")


def test_token_command_prints_the_token_on_its_last_line(sessions_dir: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as done:
        main(
            ["token", "--sessions-dir", str(sessions_dir), "--role", "editor", "--session", SESSION, "--expires", "7d"]
        )
    assert done.value.code == 0
    lines = capsys.readouterr().out.strip().splitlines()
    grant = TokenStore(sessions_dir).resolve(lines[-1])
    assert grant is not None and grant.role == Role.editor and grant.session == SESSION and grant.expires
    with pytest.raises(SystemExit) as done:
        main(["token", "--sessions-dir", str(sessions_dir), "--role", "viewer", "--session", "missing"])
    assert done.value.code == 2 and "no session 'missing'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["revoke", "--sessions-dir", str(sessions_dir), grant.id])
    assert TokenStore(sessions_dir).resolve(lines[-1]) is None
    # the server's own flags still parse without a subcommand (make run HOST=...)
    assert serve_parser().parse_args(["--host", "0.0.0.0", "--port", "9000"]).port == 9000


# ------------------------------------------------------------------ who may do what


def test_without_a_token_every_request_is_401(shared: TestClient) -> None:
    for path in ["/", f"/sessions/{SESSION}", "/api/sessions", f"/api/sessions/{SESSION}", "/openapi.json"]:
        response = shared.get(path)
        assert response.status_code == 401, path
        assert response.headers["www-authenticate"].startswith("Bearer")
    for method, path, _role in operations(shared):
        assert shared.request(method, path, json={}).status_code == 401, (method, path)
    assert shared.get("/api/sessions", headers={"Authorization": "Bearer wrong"}).status_code == 401


def test_viewer_is_refused_every_state_change_and_each_role_only_what_it_may(shared: TestClient) -> None:
    ops = operations(shared)
    assert len(ops) >= 15
    for role in (Role.viewer, Role.reviewer, Role.editor):
        headers = bearer(shared, role)
        for method, path, required in ops:
            response = shared.request(method, path, json={}, headers=headers)
            if role < Role.parse(required):
                assert response.status_code == 403, (role, method, path, response.text)
                assert f"needs {required}" in response.json()["detail"]
            else:
                assert response.status_code not in (401, 403), (role, method, path, response.text)
            if role == Role.editor:
                break  # an editor's requests really change the session: one is enough here
    viewer = bearer(shared, Role.viewer)
    assert shared.get(f"/api/sessions/{SESSION}/poses", headers=viewer).status_code == 200  # look
    assert shared.get(f"/api/sessions/{SESSION}/export/poses", headers=viewer).status_code == 200  # export


def test_reviewer_decides_loops_but_does_not_move_scans(shared: TestClient) -> None:
    reviewer = bearer(shared, Role.reviewer, SESSION)
    accept = shared.post(f"/api/sessions/{SESSION}/loops/0/accept", json={}, headers=reviewer)
    assert accept.status_code == 404  # allowed, but there is no hypothesis 0 yet
    move = shared.post(f"/api/sessions/{SESSION}/scans/1/pose", json={"pose": np.eye(4).tolist()}, headers=reviewer)
    assert move.status_code == 403


def test_a_session_token_opens_that_session_only(shared: TestClient) -> None:
    editor = bearer(shared, Role.editor, SESSION)
    assert shared.get(f"/sessions/{SESSION}", headers=editor).status_code == 200
    assert shared.get(f"/api/sessions/{SESSION}", headers=editor).status_code == 200
    assert shared.get("/api/sessions/other", headers=editor).status_code == 403
    assert shared.get("/api/sessions", headers=editor).status_code == 403  # the list names other sessions
    assert shared.post("/api/sessions/other/undo", json={}, headers=editor).status_code == 403


def test_a_page_link_token_becomes_an_httponly_strict_cookie(shared: TestClient) -> None:
    secret, _ = shared.app.state.tokens.issue(Role.viewer, SESSION)  # type: ignore[attr-defined]
    page = shared.get(f"/sessions/{SESSION}?token={secret}")
    assert page.status_code == 200
    cookie = page.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and secret in cookie
    assert shared.get(f"/api/sessions/{SESSION}").status_code == 200  # the cookie now carries the token
    assert shared.post(f"/api/sessions/{SESSION}/undo", json={}).status_code == 403  # a viewer's cookie


def test_the_author_of_a_shared_edit_is_the_token_holder(shared: TestClient) -> None:
    editor = bearer(shared, Role.editor, SESSION, name="ann")
    pose = shared.app.state.workbench.current_poses(SESSION)[1]  # type: ignore[attr-defined]
    moved = shared.post(
        f"/api/sessions/{SESSION}/scans/1/pose",
        json={"pose": pose.tolist()},
        headers={**editor, "X-Author": "someone else"},
    )
    assert moved.status_code == 200, moved.text
    assert shared.get(f"/api/sessions/{SESSION}/journal", headers=editor).json()[-1]["author"] == "ann"


# ------------------------------------------------------------------ cross-site and host


def test_foreign_origin_and_cross_site_fetches_are_refused(shared: TestClient) -> None:
    editor = bearer(shared, Role.editor)
    url = f"/api/sessions/{SESSION}/undo"
    assert shared.post(url, json={}, headers={**editor, "Origin": "http://evil.example"}).status_code == 403
    assert shared.post(url, json={}, headers={**editor, "Origin": "null"}).status_code == 403
    assert shared.post(url, json={}, headers={**editor, "Sec-Fetch-Site": "cross-site"}).status_code == 403
    assert shared.post(url, json={}, headers={**editor, "Sec-Fetch-Site": "same-site"}).status_code == 403
    same = shared.post(url, json={}, headers={**editor, "Origin": ORIGIN, "Sec-Fetch-Site": "same-origin"})
    assert same.status_code in (200, 409)  # reached the handler (nothing to undo is 409)


def test_body_less_posts_need_json_so_simple_cross_site_requests_cannot_send_them(shared: TestClient) -> None:
    editor = bearer(shared, Role.editor)
    for what in ("undo", "redo", "loops/detect", "close-loops", "relax", "loops/0/accept"):
        url = f"/api/sessions/{SESSION}/{what}"
        assert shared.post(url, headers=editor).status_code == 415, what
        form = shared.post(url, content=b"a=1", headers={**editor, "Content-Type": "text/plain"})
        assert form.status_code == 415, what


def test_dns_rebinding_host_names_are_refused(shared: TestClient) -> None:
    editor = bearer(shared, Role.editor)
    assert shared.get("/api/sessions", headers={**editor, "Host": "evil.example:8080"}).status_code == 400
    assert shared.get("/api/sessions", headers={**editor, "Host": "localhost:8080"}).status_code == 200
    assert shared.get("/api/sessions", headers={**editor, "Host": "[::1]:8080"}).status_code == 200


def test_loopback_server_stays_open_but_still_checks_origin(sessions_dir: Path) -> None:
    with TestClient(create_app(sessions_dir, viewers=False), base_url=ORIGIN) as client:
        assert client.get("/api/sessions").status_code == 200
        assert (
            client.post(f"/api/sessions/{SESSION}/undo", json={}, headers={"Origin": "http://evil.example"}).status_code
            == 403
        )


# ------------------------------------------------------------------ the data root


def test_folder_sessions_come_only_from_the_data_root(shared: TestClient, tmp_path: Path) -> None:
    editor = bearer(shared, Role.editor)
    write_corridor_scans(tmp_path / "data" / "inside", scans=2, points=100)
    write_corridor_scans(tmp_path / "outside", scans=2, points=100)
    (tmp_path / "data" / "link").symlink_to(tmp_path / "outside")
    ok = shared.post("/api/sessions", json={"name": "In", "source": "inside"}, headers=editor)
    assert ok.status_code == 201, ok.text
    for source in (str(tmp_path / "outside"), "../outside", "link", "/etc/passwd", "/etc/no-such-file"):
        refused = shared.post("/api/sessions", json={"name": "Out", "source": source}, headers=editor)
        assert refused.status_code == 403, source
        assert "data root" in refused.json()["detail"] and "such file" not in refused.json()["detail"]
    assert sorted(p.name for p in (tmp_path / "sessions").iterdir() if p.is_dir()) == ["In", "corridor", "other"]


def test_a_shared_server_without_data_root_refuses_folder_sessions(sessions_dir: Path, tmp_path: Path) -> None:
    write_corridor_scans(tmp_path / "scans", scans=2, points=100)
    with TestClient(create_app(sessions_dir, viewers=False, bind_host="0.0.0.0"), base_url=ORIGIN) as client:
        editor = bearer(client, Role.editor)
        refused = client.post("/api/sessions", json={"name": "x", "source": str(tmp_path / "scans")}, headers=editor)
        assert refused.status_code == 403 and "--data-root" in refused.json()["detail"]
        assert client.get("/api/sessions").status_code == 401  # bound off loopback: tokens required


# ------------------------------------------------------------------ revisions over HTTP


def move(client: TestClient, scan: int, x: float, headers: dict[str, str]) -> Any:
    pose = np.eye(4)
    pose[:3, 3] = (x, 0.5 * scan, 0.0)
    return client.post(f"/api/sessions/{SESSION}/scans/{scan}/pose", json={"pose": pose.tolist()}, headers=headers)


def test_every_session_response_carries_its_revision_and_stale_if_match_is_412(shared: TestClient) -> None:
    editor = bearer(shared, Role.editor, name="ann")
    seen = shared.get(f"/api/sessions/{SESSION}", headers=editor)
    assert seen.headers["etag"] == '"0"'
    first = move(shared, 1, 3.0, {**editor, "If-Match": seen.headers["etag"]})
    assert first.status_code == 200 and first.headers["etag"] == '"1"'
    stale = move(shared, 2, 7.0, {**editor, "If-Match": '"0"'})
    assert stale.status_code == 412
    assert stale.json()["head"] == 1
    assert stale.json()["since"] == [
        {"revision": 1, "kind": "manual_move", "author": "ann", "time": stale.json()["since"][0]["time"]}
    ]
    poses = shared.app.state.workbench.current_poses(SESSION)  # type: ignore[attr-defined]
    assert poses[2][0, 3] != pytest.approx(7.0)  # not applied
    assert (
        shared.post(f"/api/sessions/{SESSION}/undo", json={}, headers={**editor, "If-Match": '"0"'}).status_code == 412
    )
    assert move(shared, 2, 7.0, {**editor, "If-Match": "bogus"}).status_code == 422  # refused, not ignored
    assert move(shared, 2, 7.0, {**editor, "If-Match": '"1"'}).status_code == 200


# ------------------------------------------------------------------ share links


def test_owners_create_and_revoke_share_links(shared: TestClient) -> None:
    owner = bearer(shared, Role.owner, SESSION, name="olga")
    assert shared.get("/api/me", headers=owner).json() == {
        "role": "owner",
        "name": "olga",
        "session": SESSION,
        "open": False,
    }
    created = shared.post(
        f"/api/sessions/{SESSION}/tokens", json={"role": "viewer", "name": "vic", "expires": "1d"}, headers=owner
    )
    assert created.status_code == 201, created.text
    link = created.json()["link"]
    assert link.startswith(f"{ORIGIN}/sessions/{SESSION}?token=")
    viewer = {"Authorization": f"Bearer {created.json()['token']}"}
    assert shared.get("/api/me", headers=viewer).json()["role"] == "viewer"
    listed = shared.get(f"/api/sessions/{SESSION}/tokens", headers=owner).json()
    assert {g["name"] for g in listed} == {"olga", "vic"}
    assert all("token" not in g and "digest" not in g for g in listed)
    assert shared.get(f"/api/sessions/{SESSION}/tokens", headers=viewer).status_code == 403
    editor = bearer(shared, Role.editor, SESSION)
    denied = shared.post(f"/api/sessions/{SESSION}/tokens", json={"role": "viewer", "name": "x"}, headers=editor)
    assert denied.status_code == 403
    revoked = shared.delete(f"/api/sessions/{SESSION}/tokens/{created.json()['grant']['id']}", headers=owner)
    assert revoked.status_code == 200 and revoked.json()["revoked"] is True
    assert shared.get(f"/api/sessions/{SESSION}", headers=viewer).status_code == 401
    bad = shared.post(f"/api/sessions/{SESSION}/tokens", json={"name": "x", "expires": "soon"}, headers=owner)
    assert bad.status_code == 422 and "'soon' is not a duration" in bad.json()["detail"]


def test_every_operation_documents_what_the_guard_may_answer(shared: TestClient) -> None:
    for template, methods in shared.app.openapi()["paths"].items():  # type: ignore[attr-defined]
        for method, operation in methods.items():
            documented = set(operation["responses"])
            assert {"400", "401", "403"} <= documented, (method, template)
            if method in MUTATING:
                assert {"412", "415"} <= documented, (method, template)
