"""Where numba keeps the engine's compiled kernels, so that no process compiles them twice.

Every kernel is ``numba.njit(cache=True)``: the first process compiles it (~20 s of CPU for those a
``slam6d run`` uses) and writes the machine code to disk; every later process loads it in ~10 ms
per kernel. numba looks for a writable place when a module's kernels are defined: beside the
sources (``slam6d/__pycache__``, the case of an editable or a user's own virtualenv install), then
its user-wide cache (``$XDG_CACHE_HOME/numba``, else ``~/.cache/numba``: a system-wide install run
by a user). Where neither is writable (a read-only image run by a service user without a home)
numba refuses to define the kernels at all, and importing the engine fails with "cannot cache
function ...: no locator available". :func:`kernel_cache_dir` sees that case before numba does and
names a per-user directory under the system's temporary directory instead, which lasts as long as
that directory does. ``NUMBA_CACHE_DIR``, when set, is the user's choice and always wins.

``slam6d/__init__.py`` applies it before any kernel module loads; it costs a few ``stat`` calls and
imports nothing heavy.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path

PACKAGE_CACHE = Path(__file__).resolve().parent / "__pycache__"


def _writable(directory: Path) -> bool:
    """Whether ``directory`` exists writable or could be created: its nearest existing ancestor is a
    writable directory. ``os.access`` also answers no on a read-only file system, even for root."""
    for candidate in (directory, *directory.parents):
        if candidate.exists():
            return candidate.is_dir() and os.access(candidate, os.W_OK | os.X_OK)
    return False


def numba_user_cache(environ: Mapping[str, str]) -> Path | None:
    """numba's user-wide cache directory on POSIX systems (its vendored ``appdirs``' rule), or
    ``None`` for a user without a home (no ``HOME`` and no entry in the password database)."""
    base = environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            home = environ.get("HOME") or str(Path.home())
        except RuntimeError:  # Path.home() when it cannot determine one
            return None
        base = str(Path(home) / ".cache")
    return Path(base).expanduser() / "numba"


def kernel_cache_dir(environ: Mapping[str, str] = os.environ, package_cache: Path = PACKAGE_CACHE) -> Path | None:
    """The directory numba must be told to keep the kernels in, or ``None`` where its own choice
    works (``NUMBA_CACHE_DIR`` set, the package's ``__pycache__`` or numba's user cache writable)."""
    if environ.get("NUMBA_CACHE_DIR"):
        return None
    if _writable(package_cache):
        return None
    user_cache = numba_user_cache(environ)
    if user_cache is not None and _writable(user_cache):
        return None
    import tempfile

    return Path(tempfile.gettempdir()) / f"slam6d-numba-cache-{os.getuid()}"


def use_kernel_cache(directory: Path) -> None:
    """Point numba at ``directory``: through the environment for a numba not imported yet, and its
    loaded configuration otherwise (numba reads ``NUMBA_CACHE_DIR`` once, at import)."""
    os.environ["NUMBA_CACHE_DIR"] = str(directory)
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.CACHE_DIR = str(directory)


def ensure_kernel_cache() -> None:
    """Apply :func:`kernel_cache_dir` if numba needs telling."""
    directory = kernel_cache_dir()
    if directory is not None:
        use_kernel_cache(directory)
