"""Browser-test harness: a real workbench server on a free port and Debian Chromium driven by Playwright.

The server runs in-process (uvicorn in a thread) so tests can also look at its state; Chromium
gets a fresh profile per test and software WebGL (no GPU on CI machines).
"""

from __future__ import annotations

import io
import os
import shutil
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import uvicorn
from PIL import Image

from app.resources import ResourceLimits
from app.server import create_app
from slam6d.session import Session
from tests.conftest import PROJECT_ROOT
from tests.session_fixtures import corridor_session

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--enable-unsafe-swiftshader",  # software WebGL, which viser's canvas needs without a GPU
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    def __init__(self, sessions_dir: Path, **options: Any) -> None:
        """``options`` go to ``create_app`` (e.g. ``require_token=True``: as if bound off loopback)."""
        # a view a test holds is not stopped between its pages (test_viewer_lifecycle tests stopping)
        options.setdefault("limits", ResourceLimits(viewer_grace_s=600))
        self.app = create_app(sessions_dir, **options)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning", lifespan="on")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> LiveServer:
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("workbench server did not start")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=20)

    @property
    def workbench(self):  # type: ignore[no-untyped-def]
        return self.app.state.workbench


@pytest.fixture
def corridor_sessions(tmp_path: Path) -> Path:
    """A small 6-scan session (fast to load) in a fresh sessions folder."""
    root = tmp_path / "sessions"
    corridor_session(root, scans=6, points=8000, odometry_noise=0.15, engine={"voxel_size": 0.1})
    return root


@pytest.fixture
def demo_sessions(tmp_path: Path) -> Path:
    """The bundled demo session's scans behind a session folder of its own (the repo's journal stays untouched)."""
    bundled = PROJECT_ROOT / "sessions" / "demo"
    if not (bundled / "scans").is_dir():
        message = f"bundled session scans missing at {bundled / 'scans'}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    config = Session.open(bundled).config
    root = tmp_path / "sessions"
    Session.create(
        root / "demo", config.name, bundled / "scans", config.format_name, config.frame, engine=config.engine
    )
    cache = bundled / "cache"
    if cache.is_dir():  # reuse the parsed scans if the bundled session was opened before
        shutil.copytree(cache, root / "demo" / "cache")
    return root


@pytest.fixture
def live_server() -> Iterator[Callable[..., LiveServer]]:
    servers: list[LiveServer] = []

    def start(sessions_dir: Path, **options: Any) -> LiveServer:
        server = LiveServer(sessions_dir, **options).__enter__()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.__exit__()


@pytest.fixture
def new_browser(tmp_path: Path) -> Iterator[Callable[[], object]]:
    """``new_browser()`` -> a Playwright page in a fresh Chromium profile (call twice for two users)."""
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} not found: install Debian's chromium (make system-deps)")
    from playwright.sync_api import sync_playwright

    playwright = sync_playwright().start()
    contexts: list[Any] = []

    def open_page():  # type: ignore[no-untyped-def]
        profile = tmp_path / f"profile-{len(contexts)}"
        context = playwright.chromium.launch_persistent_context(
            str(profile),
            executable_path=str(CHROMIUM),
            args=CHROMIUM_ARGS,
            headless=True,
            viewport={"width": 1280, "height": 800},
        )
        contexts.append(context)
        return context.pages[0] if context.pages else context.new_page()

    yield open_page
    for context in contexts:
        context.close()
    playwright.stop()


def viewer_frame(page):  # type: ignore[no-untyped-def]
    return page.frame_locator("#viewer")


def set_name(page, server, session_id: str, name: str, timeout: float = 30.0) -> None:  # type: ignore[no-untyped-def]
    """Type the one name field (page header); wait until the 3D view has reconnected under it and shows its panels."""
    page.locator("#author").fill(name)
    page.locator("#author").dispatch_event("change")
    names = server.app.state.viewers.get(session_id).names
    deadline = time.monotonic() + timeout
    while name not in names.connected().values():
        assert time.monotonic() < deadline, f"the 3D view never connected as {name!r}: {names.connected()}"
        time.sleep(0.05)
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=timeout * 1000)  # its panels are drawn again


def map_pixels(page, panel_fraction: float = 0.65) -> float:  # type: ignore[no-untyped-def]
    """Fraction of the 3D canvas (left of the control panel) whose colour differs from the background."""
    png = page.locator("#viewer").screenshot()
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int32)
    canvas = image[:, : int(image.shape[1] * panel_fraction)]
    # the background is the most common colour along the canvas border
    border = np.concatenate([canvas[0], canvas[-1], canvas[:, 0], canvas[:, -1]])
    values, counts = np.unique(border, axis=0, return_counts=True)
    background = values[counts.argmax()]
    different = np.abs(canvas - background).sum(axis=2) > 40
    return float(different.mean())
