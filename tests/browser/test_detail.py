"""Levels of detail in a real browser: the first view of a 60-scan map arrives, and zooming in refines the scans in front."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from slam6d.session import Session
from slam6d.simulate import SimulationConfig, simulate_session
from tests.browser.conftest import viewer_frame
from tests.browser.test_workbench import open_session, wait_for_map

pytestmark = pytest.mark.browser

BUDGET = 150_000  # of ~0.5M points: the levels must be chosen


@pytest.fixture(scope="module")
def campus_scans(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("campus") / "scans"
    simulate_session(folder, SimulationConfig(world="campus", scans=60, points_per_scan=20_000, seed=3))
    return folder


def test_first_view_arrives_and_zooming_in_raises_the_level_of_the_scan_in_front(
    campus_scans, tmp_path, live_server, new_browser, artifacts_dir
):  # type: ignore[no-untyped-def]
    root = tmp_path / "sessions"
    Session.create(root / "campus", "Campus", campus_scans, engine={"display_budget": BUDGET})
    server = live_server(root)
    page = new_browser()
    open_session(page, server, "campus", timeout=240_000)  # the first open orders the levels once
    assert wait_for_map(page) >= 0.005
    viewer = server.app.state.viewers.get("campus")
    detail = viewer.stream.detail
    total = detail.total_points
    before = list(detail.shown)
    assert total > 3 * BUDGET and detail.points_shown(before) <= BUDGET
    assert len(set(before)) > 1  # nearer scans finer: not one level for all
    page.screenshot(path=str(artifacts_dir / "detail_first_view.png"))

    # zoom in with the mouse wheel over the middle of the 3D view, as a person does
    box = page.locator("#viewer").bounding_box()
    page.mouse.move(box["x"] + box["width"] * 0.35, box["y"] + box["height"] * 0.5)
    updates = detail.updates
    for _ in range(12):
        page.mouse.wheel(0, -400)
        time.sleep(0.15)
    deadline = time.monotonic() + 60
    while detail.updates == updates or detail.camera is None:
        assert time.monotonic() < deadline, "the levels did not follow the camera"
        time.sleep(0.2)
    time.sleep(1.0)  # a last debounced pass after the final wheel step
    after = list(detail.shown)
    positions = np.array([p[:3, 3] for p in viewer.scans.poses])
    nearest = int(np.argmin(np.linalg.norm(positions - detail.camera, axis=1)))
    assert after[nearest] > before[nearest], (nearest, before[nearest], after[nearest])
    assert detail.points_shown(after) <= BUDGET
    assert [len(p) for p in viewer.scans.local] == [detail.levels.level_points[k][lv] for k, lv in enumerate(after)]
    viewer_frame(page).get_by_text("points shown").wait_for()
    page.screenshot(path=str(artifacts_dir / "detail_zoomed_in.png"))
