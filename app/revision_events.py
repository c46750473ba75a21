"""Tell a session's pages the moment its head moves: the new revision, who moved it, undo/redo state.

A page's undo and redo name the revision they step from (so a retry is one step, not two); a page
that learnt of a teammate's edit only by polling every few seconds named a stale revision in that
window and its keypress was refused. So every change of a session's head - a REST edit, a button in
the 3D view, a job's commit - is pushed to the pages listening on the session
(``/api/sessions/{id}/events``, :mod:`app.routes.events`) as it is committed: :class:`RevisionEvents`
is a listener of :meth:`app.workbench.Workbench.on_revision`, registered before the 3D views' own,
so a page knows the head no later than its 3D view shows it.

Bounded: at most :attr:`RevisionEvents.max_per_session` listeners on a session and
:attr:`RevisionEvents.max_per_grant` per token; a listener holds only the newest head (a slow page
skips what it missed, it never queues), and each head is sent once - events carry the journal
entry's id, which only grows, so two commits whose listeners run out of order never show an older
head after a newer one. Every :attr:`RevisionEvents.heartbeat_s` the stream sends a heartbeat
after checking the journal itself (a head moved by another process, a session that went away).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from app.workbench import Workbench
from slam6d.journal import Journal

HEARTBEAT = {"type": "heartbeat"}
GONE = {"type": "gone"}


def head_event(journal: Journal) -> dict[str, Any]:
    """A session's head as pages are told it: revision, the journal entry that made it current (its id,
    author, kind and time) and whether undo and redo are possible from it."""
    entry = journal.head_entry()
    return {
        "type": "revision",
        "revision": 0 if entry is None else int(entry.head or 0),  # revision 0 before it is stored
        "entry": 0 if entry is None else entry.id,
        "author": None if entry is None else entry.author,
        "kind": None if entry is None else entry.kind,
        "time": None if entry is None else entry.time,
        "can_undo": journal.can_undo(),
        "can_redo": journal.can_redo(),
    }


@dataclass(eq=False)
class Listener:
    """One page's stream: the newest head not yet sent, woken from any thread."""

    session_id: str
    grant_id: str
    loop: asyncio.AbstractEventLoop
    sent_entry: int = -1
    newest: dict[str, Any] | None = None
    wake: asyncio.Event = field(default_factory=asyncio.Event)

    def offer(self, event: dict[str, Any]) -> None:
        """Called on the committing thread: hand ``event`` to the page's loop (never blocks)."""
        with contextlib.suppress(RuntimeError):  # the server's loop is closing: the stream ends with it
            self.loop.call_soon_threadsafe(self._keep, event)

    def _keep(self, event: dict[str, Any]) -> None:
        if self.newest is None or event["entry"] > self.newest["entry"]:
            self.newest = event
            self.wake.set()

    def take(self, event: dict[str, Any]) -> dict[str, Any] | None:
        """``event`` if the page has not been sent it (or anything newer) yet, and note it as sent."""
        if event["entry"] <= self.sent_entry:
            return None
        self.sent_entry = event["entry"]
        return event

    async def next(self, timeout: float) -> dict[str, Any] | None:
        """The newest head offered since the last call, or None after ``timeout`` seconds without one."""
        try:
            await asyncio.wait_for(self.wake.wait(), timeout)
        except TimeoutError:
            return None
        self.wake.clear()
        event, self.newest = self.newest, None
        return event


class TooManyListenersError(Exception):
    """A session or token has as many event streams open as it may."""


class RevisionEvents:
    """The pages listening on each session, told of every change of its head."""

    def __init__(
        self, workbench: Workbench, max_per_session: int = 100, max_per_grant: int = 20, heartbeat_s: float = 15.0
    ) -> None:
        self.workbench = workbench
        self.max_per_session = max_per_session
        self.max_per_grant = max_per_grant
        self.heartbeat_s = heartbeat_s
        self._lock = threading.Lock()
        self._listeners: dict[str, list[Listener]] = {}
        workbench.on_revision(self._changed)

    def current(self, session_id: str) -> dict[str, Any]:
        """The session's head now (UnknownSessionError when there is no such session)."""
        return head_event(self.workbench.state(session_id).session.journal)

    def subscribe(self, session_id: str, grant_id: str) -> Listener:
        """A new listener on the running loop; TooManyListenersError when a bound is reached."""
        listener = Listener(session_id, grant_id, asyncio.get_running_loop())
        with self._lock:
            on_session = self._listeners.setdefault(session_id, [])
            per_grant = Counter(other.grant_id for others in self._listeners.values() for other in others)
            if len(on_session) >= self.max_per_session:
                raise TooManyListenersError(f"session '{session_id}' has {len(on_session)} event streams open")
            if per_grant[grant_id] >= self.max_per_grant:
                raise TooManyListenersError(f"this token has {per_grant[grant_id]} event streams open")
            on_session.append(listener)
        return listener

    def unsubscribe(self, listener: Listener) -> None:
        with self._lock:
            on_session = self._listeners.get(listener.session_id, [])
            if listener in on_session:
                on_session.remove(listener)
            if not on_session:
                self._listeners.pop(listener.session_id, None)

    def listening(self, session_id: str) -> int:
        """How many pages listen on the session (tests, the load script)."""
        with self._lock:
            return len(self._listeners.get(session_id, []))

    def _changed(self, session_id: str) -> None:
        with self._lock:
            listeners = list(self._listeners.get(session_id, []))
        if not listeners:
            return
        event = self.current(session_id)  # read once for everyone, right after the commit
        for listener in listeners:
            listener.offer(event)


__all__ = ["GONE", "HEARTBEAT", "Listener", "RevisionEvents", "TooManyListenersError", "head_event"]
