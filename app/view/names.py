"""Who is behind each browser of a 3D view: the one name a person types, in the page header.

The page keeps the name (localStorage, for its own REST calls' ``X-Author``) and mirrors it into the
``slam6d-author`` cookie, which the 3D view's websocket handshake carries through the workbench's
proxy. viser numbers its clients but shows the handshake to nobody, so the proxy announces each
arriving browser's name and connects it upstream before the next one may: the next client viser
reports is that browser. A page whose name changes reloads its 3D view, which arrives again under
the new name. Names key the journal's author (and anything else that asks who a client is).

**Any script.** HTTP header values are Latin-1, so a page sends its name in ``X-Author`` as an RFC 8187
extended value, ``UTF-8''`` followed by the percent-encoded UTF-8 bytes (``UTF-8''%E5%BC%A0%E4%BC%9F``
for 张伟); a plain value is read as it comes (a script's ASCII or Latin-1 name, or raw UTF-8 bytes as
``curl -H`` sends them). Every name - header, cookie or a token's - passes :func:`checked_name`: at
most :data:`MAX_NAME` characters, no control or text-direction characters (which would garble or
disguise the journal, comment and presence lines it is shown in).
"""

from __future__ import annotations

import asyncio
import threading
import time
import unicodedata
from collections.abc import Awaitable, Callable
from contextlib import suppress
from typing import TypeVar
from urllib.parse import unquote

T = TypeVar("T")

AUTHOR_COOKIE = "slam6d-author"
MAX_NAME = 100
_ARRIVAL_WAIT = 5.0  # s: how long one arriving browser may hold the door before the next one goes ahead


EXTENDED_VALUE_PREFIX = "utf-8''"  # RFC 8187: charset, empty language, then percent-encoded bytes
# characters that reorder or hide the text around them: a name must not disguise the line it is shown in
_DIRECTION_MARKS = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


class InvalidNameError(ValueError):
    """A name that cannot be shown as who did something (the message says why, without the field)."""


def checked_name(name: str) -> str:
    """``name`` trimmed; InvalidNameError when it is longer than :data:`MAX_NAME` characters or holds a
    control, surrogate or text-direction character."""
    text = name.strip()
    if len(text) > MAX_NAME:
        raise InvalidNameError(f"a name is at most {MAX_NAME} characters, this one has {len(text)}")
    for char in text:
        if unicodedata.category(char) in ("Cc", "Cs") or char in _DIRECTION_MARKS:
            raise InvalidNameError(f"a name may not contain the control character U+{ord(char):04X}")
    return text


def name_from_header(raw: str) -> str:
    """The name in an ``X-Author`` value as the server read it (Latin-1): an RFC 8187 extended value
    (``UTF-8''%C5%81ukasz``), raw UTF-8 bytes, or plain Latin-1 text; checked by :func:`checked_name`."""
    text = raw.strip()
    if text[: len(EXTENDED_VALUE_PREFIX)].lower() == EXTENDED_VALUE_PREFIX:
        try:
            text = unquote(text[len(EXTENDED_VALUE_PREFIX) :], encoding="utf-8", errors="strict")
        except UnicodeDecodeError:
            raise InvalidNameError("the name after UTF-8'' is not percent-encoded UTF-8") from None
    elif not text.isascii():
        # raw UTF-8 bytes (what curl -H sends) arrive as Latin-1 characters: read them as UTF-8, unless
        # they are not UTF-8 (Latin-1 text after all)
        with suppress(UnicodeError):
            text = text.encode("latin-1").decode("utf-8")
    return checked_name(text)


def name_from_cookie(value: str | None) -> str:
    """The name a page stored in its cookie (URI-encoded by the page); "" when there is none or it is not
    a valid name (a websocket handshake cannot be answered with why: the page's REST calls say it)."""
    try:
        return checked_name(unquote(value or "", encoding="utf-8", errors="strict"))
    except (InvalidNameError, UnicodeDecodeError):
        return ""


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
