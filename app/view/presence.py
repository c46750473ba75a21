"""Who is on a session's 3D view: each browser's name, role, idle time and camera; follow someone.

Viser knows its clients only by number. The session page therefore opens its 3D view under a
random *view key* (the websocket ``/viser/{id}/as/{key}``), and the websocket proxy, which knows
the browser's grant, tells this module which viser client that is: it holds the browser's first
camera message (the one that makes viser register the client) until it has announced ``(key,
grant)`` here, one browser at a time, and waits for the client to appear. From then on the client
has a name and a role, and its camera is everyone's to see:

* each other browser draws it as a small labelled frustum (in its own scene only, so nobody sees
  their own frustum);
* ``idle`` is the time since the camera last moved;
* a browser may *follow* another: its camera then takes every view the other one moves to.

Nothing here is journaled: presence is the moment, not the session's history.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.per_owner import PerOwner
from app.tokens import Grant

FRUSTUM_SCALE = 0.4  # metres from the eye to the frustum's far rectangle
FRUSTUM_COLOUR = (255, 138, 31)  # the pages' accent
REDRAW_INTERVAL = 0.1  # seconds between redraws of one browser's frustum for the others
FOV_HOLD_S = 5.0  # how long after a placement a browser's reported field of view is held to the placed one
FOV_RESENDS = 3  # at most this many re-sends per placement (a client that never takes it is not pestered)


@dataclass
class Person:
    client: Any  # viser ClientHandle
    key: str
    grant: Grant
    since: float = field(default_factory=time.time)
    last_active: float = field(default_factory=time.time)
    follows: str | None = None
    last_drawn: float = 0.0
    placed_fov: tuple[float, float, int] | None = None  # (radians, hold until, re-sends left)

    def camera(self) -> dict[str, Any]:
        camera = self.client.camera
        return {
            "position": [float(v) for v in camera.position],
            "look_at": [float(v) for v in camera.look_at],
            "up": [float(v) for v in camera.up_direction],
            "fov_deg": float(np.degrees(camera.fov)),
        }

    def as_dict(self, now: float) -> dict[str, Any]:
        return {
            "key": self.key,
            "name": self.grant.name or f"guest {self.client.client_id}",
            "role": self.grant.role.name,
            "idle_s": round(now - self.last_active, 1),
            "follows": self.follows,
            "camera": self.camera(),
        }


@dataclass(frozen=True)
class Drawn:
    client_id: int  # whose scene it is in
    frustum: Any  # viser CameraFrustumHandle (its label is its child)


class Presence:
    """The people on one session viewer (``viewer.server`` is its viser server)."""

    def __init__(self, viewer: Any) -> None:
        self.viewer = viewer
        self.lock = threading.RLock()
        self.people: dict[int, Person] = {}
        self._announced: deque[tuple[str, Grant, threading.Event]] = deque()
        # (seeing client, seen client) -> the seen one's frustum in the seeing one's scene
        self.frustums: dict[tuple[int, int], Any] = {}
        viewer.server.on_client_connect(self._connected)
        viewer.server.on_client_disconnect(self._disconnected)

    # -- who is who (the proxy announces, viser connects)

    def announce(self, key: str, grant: Grant) -> threading.Event:
        """The next client viser registers is the browser with ``key``; the event is set when it has."""
        done = threading.Event()
        with self.lock:
            self._announced.append((key, grant, done))
        return done

    def withdraw(self, done: threading.Event) -> None:
        """The announced browser did not appear in time: forget it (it stays an anonymous client)."""
        with self.lock:
            self._announced = deque(a for a in self._announced if a[2] is not done)

    def _connected(self, client: Any) -> None:
        with self.lock:
            if not self._announced:
                return  # a client the proxy did not announce (no view key): not listed
            key, grant, done = self._announced.popleft()
            person = self.people[client.client_id] = Person(client, key, grant)
            others = [p for p in self.people.values() if p is not person]
        client.camera.on_update(lambda _camera: self._moved(person))
        for other in others:  # the newcomer sees everyone already there
            self._draw(other, viewer_of=person)
        done.set()

    def _disconnected(self, client: Any) -> None:
        with self.lock:
            person = self.people.pop(client.client_id, None)
            gone = [k for k in self.frustums if client.client_id in k]
            handles = [self.frustums.pop(k) for k in gone]
            for other in self.people.values():
                if person is not None and other.follows == person.key:
                    other.follows = None
        for handle in handles:
            if handle.client_id != client.client_id:  # the leaving browser's own scene is gone with it
                handle.frustum.remove()

    # -- cameras

    def _moved(self, person: Person) -> None:
        now = time.time()
        person.last_active = now
        self._hold_fov(person, now)
        with self.lock:
            others = [p for p in self.people.values() if p is not person]
            redraw = now - person.last_drawn >= REDRAW_INTERVAL
            if redraw:
                person.last_drawn = now
        for other in others:
            if other.follows == person.key:
                _set_camera(other.client, person.camera())
            if redraw:
                self._draw(person, viewer_of=other)

    def _draw(self, person: Person, viewer_of: Person) -> None:
        """``person``'s camera as a labelled frustum in ``viewer_of``'s scene."""
        camera = person.client.camera
        name = f"/presence/{person.client.client_id}"
        scene = viewer_of.client.scene
        frustum = scene.add_camera_frustum(
            name,
            fov=float(camera.fov),
            aspect=float(camera.aspect) if camera.image_height else 1.5,
            scale=FRUSTUM_SCALE,
            color=FRUSTUM_COLOUR,
            wxyz=tuple(float(v) for v in camera.wxyz),
            position=tuple(float(v) for v in camera.position),
        )
        scene.add_label(f"{name}/label", person.grant.name or f"guest {person.client.client_id}")
        with self.lock:
            self.frustums[(viewer_of.client.client_id, person.client.client_id)] = Drawn(
                viewer_of.client.client_id, frustum
            )

    # -- what the page asks

    def listed(self) -> list[dict[str, Any]]:
        now = time.time()
        with self.lock:
            return [p.as_dict(now) for p in sorted(self.people.values(), key=lambda p: p.since)]

    def person(self, key: str) -> Person | None:
        with self.lock:
            return next((p for p in self.people.values() if p.key == key), None)

    def follow(self, key: str, target: str | None) -> None:
        """``key``'s browser takes ``target``'s view from now on (None: stop following)."""
        with self.lock:
            person, leader = self.person(key), None if target is None else self.person(target)
            if person is None:
                raise LookupError(f"no browser '{key}' on this view")
            if target is not None and (leader is None or leader is person):
                raise LookupError(f"no other browser '{target}' on this view to follow")
            step, seen = leader, set()
            while step is not None and step.follows is not None and step.key not in seen:  # no circles
                seen.add(step.key)
                if step.follows == key:
                    raise ValueError(f"{leader.grant.name or target} follows you already")  # type: ignore[union-attr]
                step = self.person(step.follows)
            person.follows = target
        if leader is not None:
            _set_camera(person.client, leader.camera())

    def place(self, key: str, camera: dict[str, Any]) -> None:
        """Move ``key``'s camera (a permalink being opened)."""
        person = self.person(key)
        if person is None:
            raise LookupError(f"no browser '{key}' on this view")
        _set_camera(person.client, camera)
        person.placed_fov = (float(np.radians(camera["fov_deg"])), time.time() + FOV_HOLD_S, FOV_RESENDS)

    @staticmethod
    def _hold_fov(person: Person, now: float) -> None:
        """Put a placed field of view back if the browser's report says it was lost.

        viser's client applies a field of view by a message of its own, and a camera report it
        made before (with its default 75°) can reach the server after it: the server then believes
        the old field of view, and so do the address and Copy link built from it. Nobody changes
        the field of view by hand in the 3D view, so for a few seconds after a placement a report
        that differs is a stale one, and the placed value is sent again.
        """
        placed = person.placed_fov
        if placed is None:
            return
        fov, until, left = placed
        if now > until or left <= 0:
            person.placed_fov = None
            return
        if abs(float(person.client.camera.fov) - fov) > 1e-4:
            person.placed_fov = (fov, until, left - 1)
            person.client.camera.fov = fov


def _set_camera(client: Any, camera: dict[str, Any]) -> None:
    with client.atomic():
        client.camera.up_direction = tuple(camera["up"])
        client.camera.position = tuple(camera["position"])
        client.camera.look_at = tuple(camera["look_at"])
        client.camera.fov = float(np.radians(camera["fov_deg"]))


presence_of: PerOwner[Any, Presence] = PerOwner(Presence)
"""The presence of a session viewer (made with the viewer, before any browser connects)."""


__all__ = ["Person", "Presence", "presence_of"]
