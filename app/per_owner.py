"""One helper object per owner (an editor per workbench, a presence per 3D view), made on first use.

The REST routes and the 3D views must share the same helper for one owner, without a global that
keeps owners alive: the table holds its owners weakly, so a helper goes when its owner goes.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import Generic, TypeVar

Owner = TypeVar("Owner")
Helper = TypeVar("Helper")


class PerOwner(Generic[Owner, Helper]):
    """``table(owner)`` is the one helper of ``owner``, made by ``make(owner)`` the first time."""

    def __init__(self, make: Callable[[Owner], Helper]) -> None:
        self._make = make
        self._helpers: weakref.WeakKeyDictionary[Owner, Helper] = weakref.WeakKeyDictionary()
        self._lock = threading.Lock()

    def __call__(self, owner: Owner) -> Helper:
        with self._lock:
            helper = self._helpers.get(owner)
            if helper is None:
                helper = self._helpers[owner] = self._make(owner)
            return helper
