"""How much of the machine the workbench may hold: running jobs, memory of opened sessions, idle 3D
views, time spent parsing. One frozen record, filled from the ``slam6d-workbench`` command line.

The memory budget is enforced by :class:`SessionMemory`: a session's scans are read into memory
when someone first needs them (a view, an edit, a job) and would otherwise stay there until the
server stops, so a server that has shown many large sessions once would hold them all. Past the
budget, the least recently used sessions that no job and no 3D view is using release their scans
and reduced models; the next request that needs them reads them again (from the session's scan
cache, so far quicker than the first time), which the user does not notice beyond that delay.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from app.jobs import default_job_limit

log = logging.getLogger("slam6d.workbench")

GIB = 1 << 30


@dataclass(frozen=True)
class ResourceLimits:
    """``max_jobs`` jobs run at once (more wait queued); opened sessions hold at most
    ``session_memory_bytes`` of scans; a 3D view nobody has looked at for ``viewer_grace_s`` seconds
    is stopped; parsing an upload may take ``parse_timeout_s`` seconds."""

    max_jobs: int = field(default_factory=default_job_limit)
    session_memory_bytes: int = 4 * GIB
    viewer_grace_s: float = 60.0
    parse_timeout_s: float = 300.0

    def __post_init__(self) -> None:
        for name in ("max_jobs", "session_memory_bytes", "viewer_grace_s", "parse_timeout_s"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{name} must be positive, got {value}")


class Loaded(Protocol):
    """What the budget needs of an opened session (:class:`app.workbench.SessionState`)."""

    last_used: float

    def held_bytes(self) -> int: ...

    def release(self) -> bool: ...


def array_bytes(arrays: Iterable[np.ndarray | None]) -> int:
    return sum(int(a.nbytes) for a in arrays if a is not None)


class SessionMemory:
    """Keeps the opened sessions' estimated bytes under ``budget``, releasing least recently used first.

    ``in_use(session_id)`` says whether something still needs a session's scans (a running or queued
    job, a 3D view): those are never released. The session used last is kept even when it alone
    exceeds the budget: it is the one a request is working on.
    """

    def __init__(self, budget: int, in_use: Callable[[str], bool]) -> None:
        self.budget = budget
        self.in_use = in_use
        self.released = 0  # how many times a session's scans were released (shown in logs and tests)
        self._lock = threading.Lock()

    def enforce(self, states: dict[str, Loaded]) -> list[str]:
        """Release sessions until the estimate fits; the ids released."""
        with self._lock:
            held = {sid: state.held_bytes() for sid, state in list(states.items())}
            total = sum(held.values())
            if total <= self.budget:
                return []
            newest = max(states, key=lambda sid: states[sid].last_used)
            released = []
            for sid in sorted(states, key=lambda sid: states[sid].last_used):
                if total <= self.budget:
                    break
                if sid == newest or not held[sid] or self.in_use(sid):
                    continue
                if states[sid].release():
                    total -= held[sid]
                    released.append(sid)
            self.released += len(released)
        for sid in released:
            log.info("session %s released from memory (budget %d MiB)", sid, self.budget >> 20)
        return released
