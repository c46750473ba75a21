"""Sharing a session on a real server: tokens on pages, REST and the websocket; what a viewer sees."""

from __future__ import annotations

import asyncio
import time
from urllib.parse import unquote

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


def test_a_comment_added_in_the_page_stays_on_its_scan_after_relaxation(corridor_sessions, live_server, new_browser):
    from app.view import comment_labels

    server = live_server(corridor_sessions, require_token=True)
    secret, _ = server.app.state.tokens.issue(Role.reviewer, "corridor", name="rita")
    page = new_browser()
    page.goto(f"{server.url}/sessions/corridor?token={secret}")
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=60_000)
    page.locator("#comments-open").click()
    form = page.locator("#comment-form")
    form.locator("[name=on]").select_option("scan")
    form.locator("[name=i]").fill("3")
    form.locator("[name=point]").fill("1 0.5 0.8")
    form.locator("[name=text]").fill("double wall here")
    form.locator("button[type=submit]").click()
    page.locator("#comment-1").get_by_text("double wall here").wait_for(timeout=10_000)
    assert "rita" in page.locator("#comment-1").inner_text()

    editor, _ = server.app.state.tokens.issue(Role.editor, "corridor", name="ed")
    started = httpx.post(
        f"{server.url}/api/sessions/corridor/relax",
        json={"method": "graph", "fixed": [0]},
        headers={"Authorization": f"Bearer {editor}"},
    )
    assert started.status_code == 202, started.text
    job = server.workbench.jobs.wait(started.json()["id"], timeout=120)
    assert job.status == "done", job.message
    pose = server.workbench.current_poses("corridor")[3]
    expected = (pose @ np.array([1.0, 0.5, 0.8, 1.0]))[:3]
    listed = httpx.get(f"{server.url}/api/sessions/corridor/comments", headers={"Authorization": f"Bearer {secret}"})
    assert listed.json()[0]["world"] == pytest.approx(expected, abs=1e-9)
    viewer = server.app.state.viewers.get("corridor")
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:  # the 3D view's label follows the scan
        labels = comment_labels._drawn.get(viewer, [])
        if labels and np.allclose(labels[0].position, expected, atol=1e-6):
            break
        time.sleep(0.2)
    assert labels and np.allclose(labels[0].position, expected, atol=1e-6)


def _wait(condition, timeout: float = 30.0, what: str = "condition"):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = condition()
        if found:
            return found
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def test_presence_shows_the_other_browser_as_a_frustum_and_follow_takes_its_view(
    corridor_sessions, live_server, new_browser
):
    from app.view.presence import presence_of

    server = live_server(corridor_sessions, require_token=True)
    pages, keys = {}, {}
    for name in ("ann", "bob"):
        secret, _ = server.app.state.tokens.issue(Role.editor, "corridor", name=name)
        page = new_browser()
        page.goto(f"{server.url}/sessions/corridor?token={secret}")
        viewer_frame(page).get_by_text("points shown").wait_for(timeout=60_000)
        pages[name] = page
    presence = presence_of(server.app.state.viewers.get("corridor"))
    people = _wait(lambda: len(presence.listed()) == 2 and presence.listed(), what="both browsers listed")
    assert sorted((p["name"], p["role"]) for p in people) == [("ann", "editor"), ("bob", "editor")]
    keys = {p["name"]: p["key"] for p in people}
    ann, bob = presence.person(keys["ann"]), presence.person(keys["bob"])
    assert ann is not None and bob is not None
    pages["bob"].locator("#people").get_by_text("ann (editor)").wait_for(timeout=10_000)
    # bob's scene holds ann's frustum where ann's camera is (and not his own)
    drawn = _wait(lambda: presence.frustums.get((bob.client.client_id, ann.client.client_id)), what="ann's frustum")
    assert np.allclose(drawn.frustum.position, ann.client.camera.position, atol=1e-6)
    assert (bob.client.client_id, bob.client.client_id) not in presence.frustums

    pages["bob"].locator(f".person[data-key='{keys['ann']}'] button").click()  # Follow
    _wait(lambda: presence.person(keys["bob"]).follows == keys["ann"], what="bob following ann")
    place = {"position": [3.0, -6.0, 4.0], "look_at": [3.0, 0.0, 0.5], "up": [0.0, 0.0, 1.0], "fov_deg": 55.0}
    ann_token = pages["ann"].context.cookies()[0]["value"]
    moved = httpx.post(
        f"{server.url}/api/sessions/corridor/presence/{keys['ann']}/camera",
        json=place,
        headers={"Authorization": f"Bearer {ann_token}"},
    )
    assert moved.status_code == 200, moved.text
    # the camera's position and look-at reach the server as separate updates: wait for both
    _wait(
        lambda: (
            np.allclose(bob.client.camera.position, place["position"], atol=1e-3)
            and np.allclose(bob.client.camera.look_at, place["look_at"], atol=1e-3)
        ),
        what="bob's view following",
    )
    assert np.allclose(bob.client.camera.look_at, place["look_at"], atol=1e-3)
    circle = httpx.post(
        f"{server.url}/api/sessions/corridor/presence/{keys['ann']}/follow",
        json={"target": keys["bob"]},
        headers={"Authorization": f"Bearer {ann_token}"},
    )
    assert circle.status_code == 409 and "follows you already" in circle.json()["detail"]
    # nobody may steer someone else's view
    other = httpx.post(
        f"{server.url}/api/sessions/corridor/presence/{keys['bob']}/camera",
        json=place,
        headers={"Authorization": f"Bearer {ann_token}"},
    )
    assert other.status_code == 403


def _address(page) -> str:  # type: ignore[no-untyped-def]
    """The page's address, asked of the page: the history API changes it without a navigation."""
    return unquote(str(page.evaluate("location.href")))


def _view_state(page) -> dict:  # type: ignore[no-untyped-def,type-arg]
    """What the page says it shows (``window.slam6dView``): key, pinned revision, camera, selection, colour."""
    return dict(page.evaluate("({...window.slam6dView, link: undefined})"))


def test_a_permalink_restores_revision_camera_selection_and_colour_in_a_fresh_browser(
    corridor_sessions, live_server, new_browser
):
    from app.view.presence import presence_of
    from app.view.selection_marker import marker_of

    server = live_server(corridor_sessions, require_token=True)
    secret, _ = server.app.state.tokens.issue(Role.editor, "corridor", name="ann")
    headers = {"Authorization": f"Bearer {secret}"}
    page = new_browser()
    page.goto(f"{server.url}/sessions/corridor?token={secret}")
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=60_000)
    live = server.app.state.viewers.get("corridor")
    presence = presence_of(live)
    key = _wait(lambda: presence.listed() and presence.listed()[0]["key"], what="ann's view")
    place = {"position": [2.0, -5.0, 3.0], "look_at": [2.5, 0.0, 0.5], "up": [0.0, 0.0, 1.0], "fov_deg": 50.0}
    assert httpx.post(
        f"{server.url}/api/sessions/corridor/presence/{key}/camera", json=place, headers=headers
    ).is_success
    form = page.locator("#select-form")  # select edge 1-2 in the page, colour by height
    form.locator("[name=kind]").select_option("edge")
    form.locator("[name=i]").fill("1")
    form.locator("[name=j]").fill("2")
    form.locator("button[type=submit]").click()
    page.locator("#colour").select_option("height")
    link = _wait(
        lambda: (
            all(p in _address(page) for p in ("cam=2.000,-5.000,3.000", "sel=edge:1-2", "colour=height"))
            and _address(page)
        ),
        what="the view in the address",
    )
    revision = server.workbench.state("corridor").session.revision
    assert f"rev={revision}&" in link and "token" not in link
    page.locator("#colour").select_option("scan")  # the shared colouring back: the link must restore it
    _wait(lambda: live.as_dict()["colour"] == "scan", what="the colouring reset")

    other, _ = server.app.state.tokens.issue(Role.editor, "corridor", name="ed")
    fresh = new_browser()
    fresh.goto(f"{link}&token={other}")
    viewer_frame(fresh).get_by_text("points shown").wait_for(timeout=120_000)  # a loaded CI machine is slow
    ed = _wait(lambda: next((p for p in presence.listed() if p["name"] == "ed"), None), what="ed's view")

    def at_the_links_camera() -> bool:
        camera = presence.person(ed["key"]).camera()
        return all(np.allclose(camera[k], place[k], atol=1e-3) for k in ("position", "look_at", "up", "fov_deg"))

    _wait(at_the_links_camera, what="the link's camera")
    time.sleep(1.0)  # the browser's camera reports made before it took the link's camera have arrived by now
    assert at_the_links_camera(), presence.person(ed["key"]).camera()
    fresh.locator("#selection-title").get_by_text("Edge 1–2").wait_for(timeout=20_000)  # shown in the panel
    state = _view_state(fresh)
    assert state["key"] == ed["key"] and state["pinned"] is None and state["selection"] == "edge:1-2"
    assert state["colour"] == "height" and fresh.locator("#colour").input_value() == "height"
    assert live.as_dict()["colour"] == "height"  # the live view recoloured (its colouring is shared)
    marker = marker_of(presence.person(ed["key"]).client)  # highlighted in ed's own scene
    assert len(marker.handles) == 1
    poses = server.workbench.current_poses("corridor")
    assert np.allclose(marker.handles[0].position, poses[1][:3, 3], atol=1e-4)  # the line starts at scan 1
    assert fresh.locator("#old-revision").is_hidden()  # the link's revision is the current one


def test_an_old_revision_link_draws_that_revision_read_only_and_its_edits_are_refused(
    corridor_sessions, live_server, new_browser
):
    from app.view.presence import presence_of

    server = live_server(corridor_sessions, require_token=True)
    secret, _ = server.app.state.tokens.issue(Role.editor, "corridor", name="ed")
    headers = {"Authorization": f"Bearer {secret}"}
    base = f"{server.url}/api/sessions/corridor"
    server.workbench.state("corridor").sequence()  # revision 0 exists once the session was first loaded
    old = server.workbench.state("corridor").session.revision
    old_poses = server.workbench.state("corridor").session.poses(old)
    pose = old_poses[2].copy()
    pose[2, 3] += 0.8
    moved = httpx.post(f"{base}/scans/2/pose", json={"pose": pose.tolist()}, headers=headers)
    assert moved.status_code == 200, moved.text
    head = moved.json()["revision"]
    assert head != old

    page = new_browser()
    page.goto(f"{server.url}/sessions/corridor?rev={old}&sel=scan:2&colour=height&token={secret}")
    banner = page.locator("#old-revision")
    banner.get_by_text(f"revision {old} as it was, read-only").wait_for(timeout=60_000)
    assert f"now at revision {head}" in banner.inner_text()
    assert "rev=" not in (page.locator("#to-head").get_attribute("href") or "")  # leads to the head
    assert page.locator("#undo").is_hidden() and page.locator("#comment-form").is_hidden()
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=120_000)
    key = _view_state(page)["key"]
    # the browser is on the old revision's own view, which draws the old pose of scan 2
    listed = _wait(
        lambda: next((p for p in httpx.get(f"{base}/presence", headers=headers).json() if p["key"] == key), None),
        what="the page's view in presence",
    )
    assert listed["revision"] == old
    drawn = httpx.get(f"{base}/view", params={"rev": old}, headers=headers).json()
    assert drawn["revision_shown"] == old and drawn["read_only"] is True
    assert np.allclose(drawn["positions"][2], old_poses[2][:3, 3], atol=1e-9)
    assert not np.allclose(drawn["positions"][2], pose[:3, 3], atol=0.5)
    rows = httpx.get(f"{base}/poses", params={"rev": old}, headers=headers).text.splitlines()
    assert np.allclose(drawn["positions"][2], np.array(rows[2].split(), float).reshape(3, 4)[:, 3], atol=1e-6)
    page.locator("#selection-title").get_by_text("Scan 2").wait_for(timeout=20_000)
    assert f"revision {old}" in page.locator("#selection-detail").inner_text()
    state = _view_state(page)
    assert state["pinned"] == old and state["selection"] == "scan:2" and state["colour"] == "height"
    view = server.app.state.revision_views.get("corridor", old)
    person = presence_of(view).person(key)
    assert person is not None and view.as_dict()["colours"][str(person.client.client_id)] == "height"
    assert server.app.state.viewers.get("corridor").as_dict()["colour"] == "scan"  # nobody else's view changed
    _wait(lambda: f"rev={old}" in _address(page) and "sel=scan:2" in _address(page), what="the address")

    # an edit from this page is refused by the server, not only hidden: show the form and send a comment
    page.evaluate(
        "document.getElementById('comments').hidden = false; document.getElementById('comment-form').hidden = false"
    )
    form = page.locator("#comment-form")
    form.locator("[name=i]").fill("2")
    form.locator("[name=text]").fill("from the past")
    form.locator("button[type=submit]").click()
    page.locator("#message").get_by_text(f"the session is at revision {head}, not {old}").wait_for(timeout=10_000)
    assert httpx.get(f"{base}/comments", headers=headers).json() == []
    assert server.workbench.state("corridor").session.revision == head
