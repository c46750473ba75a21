"""A permalink's camera placed on a browser keeps its field of view against stale camera reports.

viser's client reports its camera on its own schedule; a report made before it applied the link's
field of view can reach the server after the placement. The server must then put the placed field of
view back (a few times, for a few seconds), or the address and Copy link carry the default 75°.
"""

from __future__ import annotations

import math
import time
from contextlib import nullcontext
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from app.tokens import Grant, Role
from app.view import presence as presence_module
from app.view.presence import Presence


class _Camera:
    """What the server knows of one browser's camera, and what it sent that browser."""

    def __init__(self) -> None:
        self.position = np.array([3.0, 3.0, 3.0])
        self.look_at = np.zeros(3)
        self.up_direction = np.array([0.0, 0.0, 1.0])
        self._fov = math.radians(75.0)
        self.sent_fovs: list[float] = []

    @property
    def fov(self) -> float:
        return self._fov

    @fov.setter
    def fov(self, value: float) -> None:
        self._fov = value
        self.sent_fovs.append(value)

    def on_update(self, _callback: Any) -> None:
        """Presence listens for reports; the tests deliver them by calling ``_moved`` themselves."""

    def report(self, fov_deg: float) -> None:
        """A camera message from the browser (viser replaces its whole state with it)."""
        self._fov = math.radians(fov_deg)


def _presence_with_one_browser() -> tuple[Presence, Any, _Camera]:
    server = SimpleNamespace(on_client_connect=lambda _cb: None, on_client_disconnect=lambda _cb: None)
    presence = Presence(SimpleNamespace(server=server))
    camera = _Camera()
    client = SimpleNamespace(client_id=1, camera=camera, atomic=nullcontext)
    presence.announce(
        "k",
        Grant(
            id="g1",
            role=Role.viewer,
            session="s",
            name="ann",
            created="2026-11-24T00:00:00Z",
            expires=None,
            revoked=False,
        ),
    )
    presence._connected(client)
    return presence, presence.person("k"), camera


PLACE = {"position": [2.0, -5.0, 3.0], "look_at": [2.5, 0.0, 0.5], "up": [0.0, 0.0, 1.0], "fov_deg": 50.0}


def test_a_stale_report_after_a_placement_gets_the_placed_field_of_view_back() -> None:
    presence, person, camera = _presence_with_one_browser()
    presence.place("k", PLACE)
    camera.report(75.0)  # the browser's report from before it took the link's field of view
    presence._moved(person)
    assert person.camera()["fov_deg"] == pytest.approx(50.0, abs=1e-6)
    assert camera.sent_fovs[-1] == pytest.approx(math.radians(50.0))


def test_the_hold_gives_up_after_a_few_resends_and_after_its_time() -> None:
    presence, person, camera = _presence_with_one_browser()
    presence.place("k", PLACE)
    sent_by_place = len(camera.sent_fovs)
    for _ in range(presence_module.FOV_RESENDS + 3):  # a client that never takes it
        camera.report(75.0)
        presence._moved(person)
    assert len(camera.sent_fovs) - sent_by_place == presence_module.FOV_RESENDS
    assert person.camera()["fov_deg"] == pytest.approx(75.0)

    presence.place("k", PLACE)
    assert person.placed_fov is not None
    fov, _until, left = person.placed_fov
    person.placed_fov = (fov, time.time() - 1.0, left)  # the hold is over: a later change is the browser's own
    camera.report(60.0)
    presence._moved(person)
    assert person.camera()["fov_deg"] == pytest.approx(60.0)
