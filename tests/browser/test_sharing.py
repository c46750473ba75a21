"""Sharing a session on a real server: tokens on pages, REST and the websocket; what a viewer sees."""

from __future__ import annotations

import asyncio

import httpx
import numpy as np
import pytest
import websockets
from websockets.asyncio.client import connect

from app.tokens import Role
from tests.browser.conftest import viewer_frame
from tests.browser.test_workbench import wait_for_map

pytestmark = pytest.mark.browser


def handshake_status(url: str, headers: dict[str, str]) -> int:
    """The HTTP status a websocket upgrade is answered with (101 when it opens)."""

    async def attempt() -> int:
        try:
            async with connect(url, additional_headers=headers, open_timeout=20, subprotocols=None):
                return 101
        except websockets.InvalidStatus as refused:
            return int(refused.response.status_code)

    return asyncio.run(attempt())


def test_shared_server_wants_a_token_on_pages_rest_and_websocket(corridor_sessions, live_server) -> None:
    server = live_server(corridor_sessions, require_token=True)
    ws_url = f"ws://127.0.0.1:{server.port}/viser/corridor"
    origin = {"Origin": server.url}
    for path in ("/", "/sessions/corridor", "/api/sessions", "/api/sessions/corridor", "/viser/corridor/"):
        assert httpx.get(server.url + path).status_code == 401, path
    assert httpx.post(server.url + "/api/sessions/corridor/undo", json={}).status_code == 401
    assert handshake_status(ws_url, origin) == 401

    secret, _ = server.app.state.tokens.issue(Role.viewer, "corridor", name="vic")
    bearer = {"Authorization": f"Bearer {secret}"}
    assert httpx.get(server.url + "/api/sessions/corridor", headers=bearer).status_code == 200
    assert handshake_status(ws_url, {**origin, **bearer}) == 101
    assert handshake_status(ws_url, {"Origin": "http://evil.example", **bearer}) == 403
    other, _ = server.app.state.tokens.issue(Role.owner, "someone-else")
    assert handshake_status(ws_url, {**origin, "Authorization": f"Bearer {other}"}) == 403


def test_viewer_link_shows_the_map_without_edit_controls_and_the_server_refuses_edits(
    corridor_sessions, live_server, new_browser, artifacts_dir
) -> None:
    server = live_server(corridor_sessions, require_token=True)
    secret, _ = server.app.state.tokens.issue(Role.viewer, "corridor", name="vic")
    page = new_browser()
    page.goto(f"{server.url}/sessions/corridor?token={secret}")
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=60_000)
    assert wait_for_map(page) >= 0.01
    page.locator("#role").get_by_text("vic · viewer").wait_for(timeout=10_000)
    assert "token" not in page.url  # the link's secret left the address bar
    assert page.locator("#undo").is_hidden() and page.locator("#redo").is_hidden()
    assert page.locator("#share-open").is_hidden()
    page.screenshot(path=str(artifacts_dir / "sharing_viewer.png"))
    # the page's own cookie reaches the server, and the server refuses the viewer's edit
    status = page.evaluate(
        """async () => (await fetch('/api/sessions/corridor/undo', {method: 'POST',
            headers: {'Content-Type': 'application/json'}, body: '{}'})).status"""
    )
    assert status == 403
    assert server.workbench.state("corridor").session.journal.entries() == [] or all(
        e.kind == "import" for e in server.workbench.state("corridor").session.journal.entries()
    )


def test_two_browsers_moving_different_scans_at_once_both_keep_their_moves(
    corridor_sessions, live_server, new_browser
) -> None:
    server = live_server(corridor_sessions, require_token=True)
    start = server.workbench.current_poses("corridor")
    pages = {}
    for scan, name in ((2, "ann"), (4, "bob")):
        secret, _ = server.app.state.tokens.issue(Role.editor, "corridor", name=name)
        page = new_browser()
        page.goto(f"{server.url}/sessions/corridor?token={secret}")
        page.locator("#role").get_by_text(f"{name} · editor").wait_for(timeout=30_000)
        pages[scan] = page
    targets = {}
    for scan in pages:
        targets[scan] = start[scan].copy()
        targets[scan][2, 3] += 1.0 + scan  # lift each scan by its own amount
    # both requests leave their browsers before either is answered
    for scan, page in pages.items():
        page.evaluate(
            """([scan, pose]) => { window.moved = fetch(`/api/sessions/corridor/scans/${scan}/pose`, {
                method: 'POST', headers: {'Content-Type': 'application/json'}, body: JSON.stringify({pose})
            }).then((r) => r.status); }""",
            [scan, targets[scan].tolist()],
        )
    assert {scan: page.evaluate("window.moved") for scan, page in pages.items()} == {2: 200, 4: 200}
    final = server.workbench.current_poses("corridor")
    assert np.allclose(final[2], targets[2]) and np.allclose(final[4], targets[4])
    journal = server.workbench.state("corridor").session.journal.entries()
    assert sorted(e.author for e in journal if e.kind == "manual_move") == ["ann", "bob"]
