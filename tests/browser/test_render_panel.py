"""Fly-through in a real browser: keyframes from the current view, a short render, its download."""

from __future__ import annotations

import re
import time

import imageio_ffmpeg
import numpy as np
import pytest
from playwright.sync_api import TimeoutError as PlaywrightTimeoutError

from slam6d.geometry import quaternion_to_rotation
from tests.browser.conftest import viewer_frame

pytestmark = pytest.mark.browser


def input_of(frame, label: str):  # type: ignore[no-untyped-def]
    """The input element of a labelled viser control."""
    exact = re.compile(f"^{re.escape(label)}$")
    return frame.locator("label", has_text=exact).locator("xpath=ancestor::div[2]").locator("input").first


def choose_option(frame, label: str, option: str, attempts: int = 3) -> None:  # type: ignore[no-untyped-def]
    """Pick ``option`` in a viser dropdown as a person does: open it, click the option.

    On a cold first page the panel may still be laid out while the list opens, so the option is
    never "stable" for Playwright; the list is closed and opened again (as a person would)."""
    for attempt in range(attempts):
        input_of(frame, label).click()
        try:
            frame.get_by_role("option", name=option, exact=True).click(timeout=10_000)
            return
        except PlaywrightTimeoutError:
            if attempt == attempts - 1:
                raise
            frame.locator("body").press("Escape")


def test_add_two_keyframes_render_and_download(corridor_sessions, live_server, new_browser, artifacts_dir, tmp_path):
    server = live_server(corridor_sessions)
    page = new_browser()
    page.goto(f"{server.url}/sessions/corridor")
    frame = viewer_frame(page)
    frame.get_by_text("points shown").wait_for(timeout=60_000)
    session = server.workbench.state("corridor").session

    frame.get_by_text("Fly-through", exact=True).click()
    add = frame.get_by_role("button", name="Add keyframe from view")
    add.click()
    frame.get_by_text("1 keyframe(s)").wait_for(timeout=10_000)
    # turn the view by dragging on the canvas, as a user would, then take the second keyframe
    box = page.locator("#viewer").bounding_box()
    x, y = box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.5
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 150, y + 40, steps=10)
    page.mouse.up()
    time.sleep(0.5)  # the camera reaches the server with the next camera update
    add.click()
    frame.get_by_text("2 keyframe(s)").wait_for(timeout=10_000)
    saved = session.camera_path()
    assert len(saved) == 2
    # the first keyframe is the initial view, which looks at the map's centre: the keyframe's camera z axis
    # (the renderer's viewing direction) must point there, so the browser's camera convention is the renderer's
    viewer = server.app.state.viewers.get("corridor")
    forward = quaternion_to_rotation(np.array(saved[0]["orientation_wxyz"]))[:, 2]
    to_centre = np.asarray(viewer.server.initial_camera.look_at) - saved[0]["position"]
    assert forward @ to_centre / np.linalg.norm(to_centre) > 0.999
    assert not np.allclose(saved[0]["orientation_wxyz"], saved[1]["orientation_wxyz"], atol=1e-3)
    # the preview draws one frustum per keyframe
    assert len(viewer.fly_through._frustums) == 2
    # "Go to" the first keyframe: this browser's camera returns to the first view
    choose_option(frame, "Keyframe", "1")
    frame.get_by_role("button", name="Go to").click()
    client = next(iter(viewer.server.get_clients().values()))
    deadline = time.monotonic() + 10
    while not np.allclose(client.camera.position, saved[0]["position"], atol=1e-3):
        assert time.monotonic() < deadline, f"camera at {client.camera.position}, not at keyframe 1"
        time.sleep(0.05)
    # "Down" swaps it with the second one, saved at once
    frame.get_by_role("button", name="Down").click()
    deadline = time.monotonic() + 10
    while [k["position"] for k in session.camera_path()] != [saved[1]["position"], saved[0]["position"]]:
        assert time.monotonic() < deadline, "the keyframes were not reordered"
        time.sleep(0.05)

    choose_option(frame, "Size", "320x240")
    frames_input = input_of(frame, "Frames (0: from path)")
    frames_input.fill("10")
    frames_input.press("Enter")
    deadline = time.monotonic() + 5
    while viewer.fly_through.frames.value != 10 or viewer.fly_through.size.value != "320x240":
        assert time.monotonic() < deadline, "size/frames did not reach the server"
        time.sleep(0.05)
    frame.get_by_role("button", name="Render video").click()
    link = frame.locator("a.render-download").first
    link.wait_for(timeout=30_000)
    page.screenshot(path=str(artifacts_dir / "workbench_render_panel.png"))
    with page.expect_download(timeout=10_000) as download_info:
        link.click()
    target = tmp_path / "download.mp4"
    download_info.value.save_as(target)

    assert target.read_bytes()[4:8] == b"ftyp"
    reader = imageio_ffmpeg.read_frames(str(target))
    meta = reader.__next__()
    images = [np.frombuffer(f, np.uint8).reshape(240, 320, 3) for f in reader]
    assert meta["size"] == (320, 240) and len(images) == 10
    assert max(float(img.std()) for img in images) > 5.0  # the map is in the frames, not just background
    jobs = [j for j in server.workbench.jobs.for_session("corridor") if j.kind == "render"]
    assert len(jobs) == 1 and jobs[0].result["path"] == "keyframes"
