"""Errors a user can act on: each names the file (and line) that caused it."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


class Slam6dError(Exception):
    """Base class for every error the engine raises on purpose."""


class FormatError(Slam6dError):
    """A file could not be read as the format it claims to be."""

    def __init__(self, path: Path | str, message: str, line: int | None = None) -> None:
        self.path = Path(path)
        self.line = line
        self.reason = message
        where = f"{self.path}:{line}" if line is not None else f"{self.path}"
        super().__init__(f"{where}: {message}")


class EmptyScanError(Slam6dError):
    """A scan has no usable points left (after dropping no-echo, NaN/inf and range-filtered points)."""

    def __init__(self, path: Path | str, detail: str = "") -> None:
        self.path = Path(path)
        super().__init__(f"{self.path}: scan has no usable points{': ' + detail if detail else ''}")


class Cancelled(Slam6dError):  # noqa: N818 - reads as "the run was cancelled"
    """The caller's ``cancel()`` check turned true; the step stopped and kept nothing half-done.

    One type for every long engine call (pipeline runs, relaxation, renders) and the workbench's
    jobs, so a cancelled job is recognised by its type wherever it was stopped.
    """


class RegistrationError(Slam6dError):
    """Registration could not produce a result (e.g. no point pairs within the max distance)."""


class RelaxationError(Slam6dError):
    """Global relaxation cannot run or did not produce a usable result; the message says why."""


class DisconnectedGraphError(RelaxationError):
    """Some scans share no edge path with a fixed scan, so their poses are undetermined.

    ``components`` holds every connected component of the graph (scan indices, each sorted, the
    components ordered by their first scan), so a caller can relax each on its own and show the
    operator which groups to bridge.
    """

    def __init__(self, message: str, components: list[list[int]]) -> None:
        self.components = components
        super().__init__(message)


class SessionError(Slam6dError):
    """A session folder is missing, malformed, or an operation on its journal is impossible."""

    def __init__(self, path: Path | str, message: str) -> None:
        self.path = Path(path)
        self.reason = message
        super().__init__(f"{self.path}: {message}")


class InvalidValueError(Slam6dError, ValueError):
    """A value handed to the engine is not acceptable (not rigid, not finite, out of range).

    ``field`` names where it came from (``poses[3]``, ``keyframes[0].orientation_wxyz``) so an API
    can answer 422 pointing at the right part of a request. It is also a ``ValueError``, so callers
    that guarded a conversion with ``except ValueError`` keep working.
    """

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.reason = message
        super().__init__(f"{field}: {message}")


def one_of(choices: Mapping[str, T], name: str, what: str) -> T:
    """The entry of ``choices`` called ``name``; a ValueError naming every choice when there is none
    (a simulation's worlds, sensors and motions are picked by name on the command line)."""
    if name not in choices:
        raise ValueError(f"unknown {what} '{name}'; choose one of {', '.join(choices)}")
    return choices[name]
