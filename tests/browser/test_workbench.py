"""The workbench in a real browser: the map is drawn, edits reach every browser on a session."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from tests.browser.conftest import map_pixels, set_name, viewer_frame

pytestmark = pytest.mark.browser


def open_session(page, server, session_id: str, timeout: float = 60_000) -> None:  # type: ignore[no-untyped-def]
    page.goto(f"{server.url}/sessions/{session_id}", timeout=timeout)  # the first page of a run starts cold
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=timeout)


def wait_for_map(page, minimum: float = 0.01, timeout: float = 20.0) -> float:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    fraction = 0.0
    while time.monotonic() < deadline:
        fraction = map_pixels(page)
        if fraction >= minimum:
            return fraction
        time.sleep(0.3)
    return fraction


def test_bundled_session_canvas_shows_the_map(demo_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(demo_sessions)
    page = new_browser()
    open_session(page, server, "demo", timeout=180_000)
    fraction = wait_for_map(page)
    page.screenshot(path=str(artifacts_dir / "workbench_demo.png"))
    assert fraction >= 0.01, f"only {fraction:.2%} of the canvas differs from the background"
    view = server.app.state.viewers.get("demo").as_dict()
    assert view["ready"] and view["error"] is None and view["points_shown"] > 0


def test_corridor_map_is_drawn_through_the_single_port(corridor_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(corridor_sessions)
    page = new_browser()
    sockets = []
    page.on("websocket", lambda ws: sockets.append(ws.url))
    open_session(page, server, "corridor")
    assert wait_for_map(page) >= 0.01
    page.screenshot(path=str(artifacts_dir / "workbench_corridor.png"))
    # two websockets, both through the workbench's port: the 3D view under the page's own view key
    # (presence) and the session's event stream (each new head, as it is committed)
    assert len(sockets) == 2, sockets
    viser, events = sorted(sockets, reverse=True)
    assert re.fullmatch(rf"ws://127\.0\.0\.1:{server.port}/viser/corridor/as/[0-9a-f]{{16}}", viser)
    assert events == f"ws://127.0.0.1:{server.port}/api/sessions/corridor/events"


def client_script(page):  # type: ignore[no-untyped-def]
    """How the 3D view's page got viser's client script: its resource timing entry (bytes on the wire and unpacked)."""
    frame = page.frame(url=re.compile(r"/viser/"))
    entries = frame.evaluate("performance.getEntriesByType('resource').map((e) => e.toJSON())")
    scripts = [e for e in entries if re.search(r"/viser-client/[0-9a-f]{16}/app\.js$", e["name"])]
    assert len(scripts) == 1, [e["name"] for e in entries]
    return scripts[0]


def test_the_3d_client_comes_gzipped_once_and_from_the_browsers_cache_after(
    corridor_sessions, live_server, new_browser
):
    server = live_server(corridor_sessions)
    page = new_browser()
    open_session(page, server, "corridor")
    assert wait_for_map(page) >= 0.01
    first = client_script(page)
    assert first["transferSize"] > 0 and first["encodedBodySize"] < 0.4 * first["decodedBodySize"]  # gzip
    page.goto("about:blank")
    open_session(page, server, "corridor")  # the session again: the script is not asked for again
    assert wait_for_map(page) >= 0.01
    again = client_script(page)
    assert again["transferSize"] == 0 and again["decodedBodySize"] == first["decodedBodySize"]


def test_second_browser_sees_the_first_ones_edit(corridor_sessions, live_server, new_browser, artifacts_dir):
    from app.view.presence import presence_of

    server = live_server(corridor_sessions)
    workbench = server.workbench
    poses = workbench.current_poses("corridor")
    poses[3] = poses[3].copy()
    poses[3][2, 3] += 2.0  # lift one scan by 2 m: an edit someone made earlier
    workbench.commit("corridor", poses, "ana", "manual_move", {"scan": 3})

    first, second = new_browser(), new_browser()
    open_session(first, server, "corridor")
    open_session(second, server, "corridor")
    viewer_frame(second).get_by_text("revision 1", exact=False).first.wait_for(timeout=10_000)

    first.locator("#author").fill("张伟")  # not Latin-1: the page sends it percent-encoded
    first.locator("#author").dispatch_event("change")
    viewer = server.app.state.viewers.get("corridor")
    presence = presence_of(viewer)
    deadline = time.monotonic() + 20  # the 3D view reconnects under the new name
    while "张伟" not in [p["name"] for p in presence.listed()] and time.monotonic() < deadline:
        time.sleep(0.1)
    assert "张伟" in [p["name"] for p in presence.listed()]
    second.locator("#people").get_by_text("张伟 (owner)").wait_for(timeout=20_000)
    # the session pages are told each new head; they do not ask for it (a poll every few seconds left
    # their shortcuts naming a stale revision in between, and the keypress was refused)
    reads: dict[str, list[str]] = {"first": [], "second": []}
    for name, page in (("first", first), ("second", second)):
        page.on("request", lambda r, n=name: reads[n].append(r.url) if r.url.endswith("/sessions/corridor") else None)
    first.locator("#undo").click()
    # the second browser's 3D view reports the new revision without reloading
    viewer_frame(second).get_by_text("revision 0", exact=False).first.wait_for(timeout=10_000)
    second.screenshot(path=str(artifacts_dir / "workbench_second_browser.png"))
    assert viewer.scans.poses[3][2, 3] == pytest.approx(workbench.current_poses("corridor")[3][2, 3])
    assert np.allclose(viewer.scans.poses[3], workbench.current_poses("corridor")[3])
    undo = workbench.state("corridor").session.journal.entries()[-1]
    assert (undo.kind, undo.author) == ("undo", "张伟")
    # Ctrl+Shift+Z in the second browser the moment its 3D view shows the undo: the page was told the new
    # revision as it was committed (it names it, so a retry is one step), so the redo applies for both
    assert reads["second"] == [], "the second page read the session instead of being told"
    second.locator("body").press("Control+Shift+Z")
    viewer_frame(first).get_by_text("revision 1", exact=False).first.wait_for(timeout=10_000)
    assert workbench.state("corridor").session.revision == 1
    # and back in the first browser at once: its Ctrl+Z steps from the redo it has just been shown
    assert len(reads["first"]) == 1  # its own read after its undo, no poll
    first.locator("body").press("Control+Z")
    viewer_frame(second).get_by_text("revision 0", exact=False).first.wait_for(timeout=10_000)
    assert workbench.state("corridor").session.revision == 0
    steps = [(e.kind, e.author) for e in workbench.state("corridor").session.journal.entries()[-3:]]
    assert steps == [("undo", "张伟"), ("redo", "anonymous"), ("undo", "张伟")]
    assert first.locator("#message").text_content() == second.locator("#message").text_content() == ""


def test_step_one_icp_iteration(corridor_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(corridor_sessions)
    page = new_browser()
    open_session(page, server, "corridor")
    frame = viewer_frame(page)
    viewer = server.app.state.viewers.get("corridor")
    before = viewer.stream.pose_updates
    for _ in range(5):  # the first step starts a scan (and may search an initial guess); then ICP iterates
        events = 0 if viewer.stepper is None else viewer.stepper.events
        frame.get_by_role("button", name="Step ICP iteration").click()
        deadline = time.monotonic() + 30
        while viewer.stepper is None or viewer.stepper.events == events:
            assert time.monotonic() < deadline, "no step happened"
            time.sleep(0.1)
        if viewer.stepper.history:
            break
    frame.get_by_text(re.compile(r"scan \d+ · iteration \d+ · RMS [0-9.]+ m · \d+ pairs")).wait_for(timeout=10_000)
    page.screenshot(path=str(artifacts_dir / "workbench_icp_step.png"))
    state = viewer.stepper.as_dict()
    assert state["iterations"] == 1 and state["current"] is not None and state["model"]
    assert viewer.stream.pose_updates > before
    assert server.workbench.state("corridor").session.revision == 0  # nothing is stored mid-run


def test_run_registration_and_see_progress_finish(corridor_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(corridor_sessions)
    page = new_browser()
    open_session(page, server, "corridor")
    frame = viewer_frame(page)
    set_name(page, server, "corridor", "carla")  # one field: the page header's name acts in the 3D view too
    assert frame.get_by_text("Your name").count() == 0 and page.get_by_text("Your name").count() == 1
    frame.get_by_role("button", name="Run registration").click()
    deadline = time.monotonic() + 5
    while not server.workbench.jobs.for_session("corridor"):
        assert time.monotonic() < deadline, "the button started no job"
        time.sleep(0.05)
    job = server.workbench.jobs.wait(server.workbench.jobs.for_session("corridor")[0].id, timeout=240)
    assert job.status == "done", job.message
    frame.get_by_text("revision 1", exact=False).first.wait_for(timeout=10_000)
    page.screenshot(path=str(artifacts_dir / "workbench_registered.png"))
    entry = next(e for e in server.workbench.state("corridor").session.journal.entries() if e.revision == 1)
    assert (entry.kind, entry.author) == ("register", "carla")
