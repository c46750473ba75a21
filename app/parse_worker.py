"""A new session's scans are parsed in a child process under a time limit, so no upload can hold the server.

Parsing an upload proves every file reads (a bad one is refused with its name and line before
anything is kept). Done on a thread of the server, a file that is slow to parse - huge, or built
to be - would hold that thread, and its memory, for as long as it liked: a deadline checked
between files cannot stop a reader inside one file. In a child process it can be stopped: when
the limit passes, the child is killed (its memory goes with it), the caller is told which file it
was reading, and the caller removes the half-made session folder.

The children come from a *forkserver* (a clean process started once, with the readers imported),
not from forking the server itself, whose threads (views, jobs, the event loop) may hold locks
at the moment of a fork. Starting a child costs milliseconds after the first; that start is
bounded apart (:data:`START_TIMEOUT_S`) and the parse limit counts from when the child begins
reading.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from app.errors import ParseTimeoutError, UploadError
from slam6d.errors import Slam6dError

PARSE_NICENESS = 10  # added to the child's nice value
START_TIMEOUT_S = 60.0  # a forkserver's first start imports numpy and the readers; later ones fork at once
_PRELOAD = ["slam6d.session", "slam6d.io.registry"]
_context_lock = threading.Lock()
_context: Any = None


def _forkserver() -> Any:
    global _context
    with _context_lock:
        if _context is None:
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(_PRELOAD)
            _context = context
        return _context


def parse_session_scans(folder: Path, timeout_s: float, label: str = "the upload") -> int:
    """Parse the scans of the session in ``folder`` (writing its scan cache and revision 0) in a child
    process; the number of scans. :class:`ParseTimeoutError` (422) naming the file being read when
    ``timeout_s`` passed; :class:`UploadError` (422) with the reader's message for a bad file."""
    context = _forkserver()
    receiver, sender = context.Pipe(duplex=False)
    child = context.Process(target=_parse_in_child, args=(str(folder), sender), name="slam6d-parse", daemon=True)
    child.start()
    sender.close()
    files: list[str] = []
    done = 0
    deadline = time.monotonic() + START_TIMEOUT_S
    try:
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not receiver.poll(remaining):
                if not files:
                    raise ParseTimeoutError(f"{label}: the parser did not start within {START_TIMEOUT_S:g} s")
                doing = f"parsing {files[done]}" if done < len(files) else "writing the scan cache"
                raise ParseTimeoutError(
                    f"{label}: {doing} took longer than the server's limit of {timeout_s:g} s "
                    f"({done} of {len(files)} files read); nothing was kept"
                )
            try:
                message = receiver.recv()
            except EOFError:  # the child died without a word (killed for memory, or a reader crashed)
                child.join(5)
                at = files[done] if done < len(files) else label
                raise UploadError(
                    f"{label}: the parser stopped while reading {at} (exit code {child.exitcode})"
                ) from None
            kind = message[0]
            if kind == "files":
                files = list(message[1])
                deadline = time.monotonic() + timeout_s  # the limit counts from the first read
            elif kind == "read":
                done = int(message[1])
            elif kind == "error":  # named inside the session ("scans/scan000.3d:2: ..."), not by server path
                raise UploadError(str(message[1]).replace(f"{folder.resolve()}/", "").replace(f"{folder}/", ""))
            else:
                return int(message[1])
    finally:
        if child.is_alive():
            child.kill()
        child.join(5)
        receiver.close()


def _parse_in_child(folder: str, report: Connection) -> None:
    """In the child: list the files, parse them (reporting each one read), say how it ended.

    At a lower priority than the server: on a busy machine the parse waits, not the other requests."""
    from slam6d.session import Session

    os.nice(PARSE_NICENESS)

    try:
        session = Session.open(folder)
        report.send(("files", [p.name for p in session.scan_files()]))
        sequence = session.load_sequence(lambda done, _total: report.send(("read", done)))
        report.send(("done", len(sequence)))
    except Slam6dError as exc:  # the reader's own message: the file and the line
        report.send(("error", str(exc)))
    except Exception as exc:  # anything else is still the upload's fault, named by type
        report.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        report.close()
