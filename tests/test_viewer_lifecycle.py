"""A session's 3D view (a viser server) runs while browsers look at it and stops after its last one left.

The "browser" here speaks viser's own protocol: it connects to the view's websocket with the client's
subprotocol and sends the camera message that makes viser count it as a client, as the web page does.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest
import viser
from websockets.sync.client import ClientConnection, connect

from app.resources import ResourceLimits
from app.server import create_app
from tests.session_fixtures import corridor_session
from tests.viser_protocol import CAMERA as CAMERA_MESSAGE
from tests.viser_protocol import encoded

GRACE = 2.0

CAMERA = encoded(CAMERA_MESSAGE)


def until(condition: Callable[[], bool], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.05)


def browser(port: int) -> ClientConnection:
    socket = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)  # type: ignore[list-item]
    socket.send(CAMERA)
    return socket


@pytest.fixture
def app(tmp_path):  # type: ignore[no-untyped-def]
    corridor_session(tmp_path / "sessions", scans=3, points=500)
    app = create_app(tmp_path / "sessions", limits=ResourceLimits(viewer_grace_s=GRACE))
    yield app
    app.state.viewers.stop_all()


def test_a_view_runs_while_a_browser_looks_and_stops_after_the_last_one_left(app):
    registry = app.state.viewers
    view = registry.get("corridor")
    assert view.ready.wait(30) and view.error is None
    first, second = browser(view.port), browser(view.port)
    until(lambda: len(view.server.get_clients()) == 2)
    time.sleep(3 * GRACE)
    assert registry.existing("corridor") is view and not view.stopped  # watched: kept past the grace
    first.close()
    until(lambda: len(view.server.get_clients()) == 1)
    time.sleep(3 * GRACE)
    assert registry.existing("corridor") is view  # one browser is enough
    second.close()
    until(lambda: registry.existing("corridor") is None)
    assert view.stopped and registry.stopped_idle == 1

    # a browser coming back starts it again, transparently
    again = registry.get("corridor")
    assert again is not view and again.ready.wait(30) and again.error is None
    socket = browser(again.port)
    until(lambda: len(again.server.get_clients()) == 1)
    socket.close()


def test_a_view_no_browser_came_to_is_stopped_and_its_session_may_be_released(app):
    registry, workbench = app.state.viewers, app.state.workbench
    view = registry.get("corridor")
    assert view.ready.wait(30)
    assert workbench._in_use("corridor")  # a view holds its session's scans
    until(lambda: registry.existing("corridor") is None)
    assert view.stopped and not workbench._in_use("corridor")


def test_a_view_with_a_job_running_is_kept(app):
    registry, workbench = app.state.viewers, app.state.workbench
    view = registry.get("corridor")
    assert view.ready.wait(30)
    from threading import Event

    release = Event()
    job = workbench.jobs.submit("corridor", "relax", lambda progress, cancel: {"waited": release.wait(60)})
    time.sleep(3 * GRACE)
    assert registry.existing("corridor") is view  # the job reports its progress there
    release.set()
    assert workbench.jobs.wait(job.id, 10).status == "done"
    until(lambda: registry.existing("corridor") is None)
