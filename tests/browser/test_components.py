"""Bridging a cut graph by hand in a real browser: the pieces show in their own colours with the
guardrail message, an edge added between a scan of each joins them, and relaxing succeeds."""

from __future__ import annotations

import httpx
import pytest

from app.editing import editor_for
from app.view.panels.edges import EdgesPanel
from tests.browser.conftest import viewer_frame
from tests.browser.test_editing import open_folder, wait_until
from tests.browser.test_render_panel import choose_option, input_of
from tests.browser.test_workbench import open_session

pytestmark = pytest.mark.browser


def test_bridge_two_components_by_hand_and_relax(corridor_sessions, live_server, new_browser, artifacts_dir):
    server = live_server(corridor_sessions)
    workbench = server.workbench
    session = workbench.state("corridor").session
    # someone deleted the sequential edge 2-3: the session's graph is two pieces, 0-2 and 3-5
    editor_for(workbench).edges.delete("corridor", 2, "ana")
    assert session.revision == 1

    page = new_browser()
    open_session(page, server, "corridor")
    frame = viewer_frame(page)
    viewer = server.app.state.viewers.get("corridor")

    # the components of the graph the chosen relaxation uses: graph relaxation over the session's edges
    open_folder(frame, "Loops & relaxation")
    choose_option(frame, "Relaxation", "graph")
    message = frame.get_by_text("disconnected: 2 components [0-2]; [3-5]", exact=False)
    message.wait_for(timeout=20_000)
    wait_until(lambda: viewer.controls.colour.value == "component", 10, "the view did not colour by component")

    def colours() -> list[tuple[int, ...]]:
        return [tuple(int(c) for c in viewer.colouring.scan_colours(k)) for k in range(6)]

    # one colour per piece
    wait_until(lambda: len(set(colours())) == 2, 10, f"not two colours: {colours()}")
    assert colours()[:3] == [colours()[0]] * 3 and colours()[3:] == [colours()[3]] * 3
    message.scroll_into_view_if_needed()
    page.screenshot(path=str(artifacts_dir / "workbench_components_split.png"))

    # pick scan 0 as A (the default) and scan 3 as B, and add the edge between them
    open_folder(frame, "Edit graph")
    scan_b = input_of(frame, "Scan B")
    scan_b.fill("3")
    scan_b.press("Enter")
    edit = next(p for p in viewer.panels if isinstance(p, EdgesPanel))
    wait_until(lambda: int(edit.scan_b.value) == 3, 5, "the number field did not reach the server")
    frame.get_by_role("button", name="Add edge A–B (ICP)").click()
    frame.get_by_text("edge 0–3 added", exact=False).wait_for(timeout=30_000)
    frame.get_by_text("all 6 scans form one connected component for graph relaxation").wait_for(timeout=20_000)
    # one colour for every scan but the two picked ones (drawn in the pick colours over it)
    wait_until(lambda: len({colours()[k] for k in (1, 2, 4, 5)}) == 1, 10, f"still split: {colours()}")
    assert set(viewer.colouring.component_of.values()) == {0}

    # relax again: graph relaxation now runs to the end
    frame.get_by_role("button", name="Relax", exact=True).click()
    wait_until(lambda: workbench.jobs.for_session("corridor"), 10, "the button started no job")
    job = workbench.jobs.wait(workbench.jobs.for_session("corridor")[-1].id, timeout=180)
    assert (job.kind, job.status) == ("relax", "done"), job.message
    assert next(e for e in session.journal.entries() if e.revision == session.revision).kind == "relax_graph"
    pieces = httpx.get(f"{server.url}/api/sessions/corridor/components", params={"method": "graph"}).json()
    assert pieces["count"] == 1 and pieces["revision"] == session.revision == 3
    page.screenshot(path=str(artifacts_dir / "workbench_components_bridged.png"))
