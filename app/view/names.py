"""Who is behind each browser of a 3D view: the one name a person types, in the page header.

The page keeps the name (localStorage, for its own REST calls' ``X-Author``) and mirrors it into the
``slam6d-author`` cookie, which the 3D view's websocket handshake carries through the workbench's
proxy. viser numbers its clients but shows the handshake to nobody, so the proxy announces each
arriving browser's name and connects it upstream before the next one may: the next client viser
reports is that browser. A page whose name changes reloads its 3D view, which arrives again under
the new name. Names key the journal's author (and anything else that asks who a client is).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar
from urllib.parse import unquote

T = TypeVar("T")

AUTHOR_COOKIE = "slam6d-author"
MAX_NAME = 100
_ARRIVAL_WAIT = 5.0  # s: how long one arriving browser may hold the door before the next one goes ahead


def name_from_cookie(value: str | None) -> str:
    """The name a page stored in its cookie (URI-encoded by the page), trimmed; "" when there is none."""
    return unquote(value or "").strip()[:MAX_NAME]


class BrowserNames:
    def __init__(self) -> None:
        self._door = asyncio.Lock()  # one arriving browser at a time (bound to the server's loop on first use)
        self._expected: str | None = None
        self._named = threading.Event()
        self._lock = threading.Lock()
        self._by_client: dict[int, str] = {}
        self._pending: asyncio.Task[None] | None = None  # closes the door once the arriving client is named

    async def admit(self, name: str, connect: Callable[[], Awaitable[T | None]]) -> T | None:
        """Connect a browser named ``name`` upstream (``connect()``; None when that failed). The door stays
        held, in the background, until viser reports the new client - which it does only once messages
        flow, so the caller goes on to forward them - or :data:`_ARRIVAL_WAIT` has passed."""
        await self._door.acquire()
        with self._lock:
            self._expected = name
            self._named.clear()
        try:
            connection = await connect()
        except BaseException:
            self._close_door()
            raise
        if connection is None:
            self._close_door()
            return None
        self._pending = asyncio.get_running_loop().create_task(self._close_door_when_named())
        return connection

    async def _close_door_when_named(self) -> None:
        deadline = time.monotonic() + _ARRIVAL_WAIT
        while not self._named.is_set() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        self._close_door()

    def _close_door(self) -> None:
        with self._lock:
            self._expected = None
        self._door.release()

    def client_connected(self, client_id: int) -> None:
        """viser reports a new client: it is the browser at the door (or, without one, a guest)."""
        with self._lock:
            name, self._expected = self._expected, None
            self._by_client[client_id] = name or f"guest-{client_id}"
            self._named.set()

    def client_left(self, client_id: int) -> None:
        with self._lock:
            self._by_client.pop(client_id, None)

    def of(self, client_id: int | None) -> str:
        """The name of a client (the journal's author for what it does); "anonymous" when unknown."""
        with self._lock:
            return self._by_client.get(-1 if client_id is None else client_id) or "anonymous"

    def connected(self) -> dict[int, str]:
        """Every connected browser's client id and name (presence, tests)."""
        with self._lock:
            return dict(self._by_client)
