"""Editing in a real browser: accept a loop, add an edge and undo it, list octree candidates."""

from __future__ import annotations

import time

import pytest

from app.view.panels.edges import EdgesPanel
from app.view.panels.guesses import GuessPanel
from slam6d.session import Session
from tests.browser.conftest import viewer_frame
from tests.browser.test_workbench import open_session
from tests.session_fixtures import write_loop_scans

pytestmark = pytest.mark.browser


@pytest.fixture
def loop_sessions(tmp_path):
    root = tmp_path / "sessions"
    write_loop_scans(root / "loop" / "scans", scans=8, points=4000)
    Session.create(root / "loop", "Loop", "scans")
    return root


def open_folder(frame, title: str) -> None:  # type: ignore[no-untyped-def]
    frame.get_by_text(title, exact=True).click()


def wait_until(condition, timeout: float = 20.0, message: str = "condition not met") -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, message
        time.sleep(0.1)


def test_detect_and_accept_a_loop(loop_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(loop_sessions)
    page = new_browser()
    page.goto(f"{server.url}/")  # the name typed on the landing page is the one the session page uses
    page.locator("#author").fill("ana")
    page.locator("#author").dispatch_event("change")
    open_session(page, server, "loop")
    frame = viewer_frame(page)
    open_folder(frame, "Loops & relaxation")
    frame.get_by_role("button", name="Detect loops").click()
    frame.get_by_text("pending", exact=True).first.wait_for(timeout=20_000)
    frame.get_by_role("button", name="Accept loop").click()
    accepted = frame.get_by_text("accepted", exact=True).first
    accepted.wait_for(timeout=10_000)
    accepted.scroll_into_view_if_needed()
    page.screenshot(path=str(artifacts_dir / "workbench_loop_accepted.png"))
    session = server.workbench.state("loop").session
    # The detect job's own record may land after the acceptance; the edit is the last non-job entry.
    entry = [e for e in session.journal.entries() if e.kind != "job"][-1]
    assert (entry.kind, entry.author) == ("accept_loop", "ana")
    assert any(e["kind"] == "loop" for e in session.graph()["loops"])


def test_add_an_edge_and_undo_it(corridor_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(corridor_sessions)
    page = new_browser()
    open_session(page, server, "corridor")
    frame = viewer_frame(page)
    open_folder(frame, "Edit graph")
    scan_b = frame.locator("label", has_text="Scan B").locator("xpath=ancestor::div[2]").locator("input")
    scan_b.fill("3")
    scan_b.press("Enter")
    viewer = server.app.state.viewers.get("corridor")
    edit = next(p for p in viewer.panels if isinstance(p, EdgesPanel))
    wait_until(lambda: int(edit.scan_b.value) == 3, 5, "the number field did not reach the server")
    frame.get_by_role("button", name="Add edge A–B (ICP)").click()
    added = frame.get_by_text("edge 0–3 added", exact=False)
    added.wait_for(timeout=20_000)
    added.scroll_into_view_if_needed()
    session = server.workbench.state("corridor").session
    assert session.revision == 1 and [(e["i"], e["j"], e["kind"]) for e in session.graph()["loops"]] == [
        (0, 3, "manual")
    ]
    page.screenshot(path=str(artifacts_dir / "workbench_edge_added.png"))
    page.locator("#undo").click()
    wait_until(lambda: session.revision == 0, 10, "undo did not happen")
    assert session.graph().get("loops", []) == []
    # the panel's edge list follows the undo (no manual edge offered any more)
    wait_until(lambda: all("manual" not in o for o in edit.edge.options), 10, "edge list not refreshed")


def test_octree_candidates_are_listed(corridor_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(corridor_sessions)
    page = new_browser()
    open_session(page, server, "corridor")
    frame = viewer_frame(page)
    open_folder(frame, "Octree guess")
    frame.get_by_role("button", name="Search candidates").click()
    frame.get_by_text("candidates", exact=False).filter(has_text="occupied").wait_for(timeout=25_000)
    winner = frame.get_by_role("cell", name="★")
    winner.wait_for(timeout=15_000)  # the winner is marked in the ranked table
    winner.scroll_into_view_if_needed()
    page.screenshot(path=str(artifacts_dir / "workbench_octree_candidates.png"))
    guess = next(p for p in server.app.state.viewers.get("corridor").panels if isinstance(p, GuessPanel))
    scores = [c["score"] for c in guess.summary["candidates"]]
    assert len(scores) == 10 and scores == sorted(scores, reverse=True)
    assert len(guess.drawn) == 12  # both scans' cubes and ten candidate frames
