"""Permalinks: what a session page's address holds - revision, camera, selection, colour mode - read and checked.

A session page's address follows its view (``/sessions/{id}?rev=R&cam=...&sel=...&colour=...``),
so copying it hands a teammate exactly what one is looking at:

``rev``
    the revision shown (an older one opens read-only, drawn as it was);
``cam``
    ten comma-separated numbers: position (3), look-at point (3), up vector (3) and vertical field
    of view in degrees, in the canonical frame (metres, z up);
``sel``
    the selected item: ``scan:K``, ``edge:I-J`` (an edge of that revision's pose graph) or
    ``loop:I-J`` (a loop hypothesis under review, by its scan pair);
``colour``
    the colour mode (:data:`app.view.controls.COLOUR_MODES`).

Every parameter is checked here, on the server, before a page or the link's REST answer uses it:
a value that is malformed, out of range or names something the session does not have is a
:class:`LinkError` (422) naming the parameter, never a 500.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from app.editing import Editor
from app.errors import WorkbenchError
from app.view.controls import COLOUR_MODES
from app.workbench import SessionState
from slam6d.session_graph import edge_key, graph_edge_list

LINK_PARAMETERS = ("rev", "cam", "sel", "colour")
COORDINATE_LIMIT = 1e6  # metres: as the camera REST body allows
_SELECTION = re.compile(r"^(scan):(\d{1,9})$|^(edge|loop):(\d{1,9})-(\d{1,9})$")


class LinkError(WorkbenchError):
    """A permalink parameter that cannot be used; the message starts with the parameter's name."""

    default_status = 422

    def __init__(self, parameter: str, problem: str) -> None:
        self.parameter = parameter
        super().__init__(f"{parameter}: {problem}")


@dataclass(frozen=True)
class Selection:
    """What a link points at: a scan (``i``) or the scan pair ``i``-``j`` of an edge or a loop hypothesis."""

    kind: str  # "scan", "edge" or "loop"
    i: int
    j: int | None = None

    @classmethod
    def pair(cls, kind: str, i: int, j: int) -> Selection:
        """An edge or loop hypothesis by its scans, named as a link names it: lower scan first."""
        return cls(kind, int(min(i, j)), int(max(i, j)))

    def text(self) -> str:
        return f"scan:{self.i}" if self.kind == "scan" else f"{self.kind}:{self.i}-{self.j}"


@dataclass(frozen=True)
class Permalink:
    revision: int | None
    camera: dict[str, Any] | None
    selection: Selection | None
    colour: str | None


def parse_link(query: Mapping[str, str]) -> Permalink:
    """The link's parameters, each checked for form and range (not yet against the session)."""
    return Permalink(
        revision=_revision(query.get("rev")),
        camera=_camera(query.get("cam")),
        selection=parse_selection(query.get("sel")),
        colour=_colour(query.get("colour")),
    )


def _revision(raw: str | None) -> int | None:
    if raw is None or raw == "":
        return None
    if not raw.isdigit() or len(raw) > 12:
        raise LinkError("rev", f"must be a revision number (got {raw[:20]!r})")
    return int(raw)


def _camera(raw: str | None) -> dict[str, Any] | None:
    if raw is None or raw == "":
        return None
    parts = raw.split(",")
    if len(parts) != 10:
        raise LinkError("cam", f"needs 10 numbers (position, look-at, up, field of view), got {len(parts)}")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise LinkError("cam", "holds something that is not a number") from None
    if not all(math.isfinite(v) and abs(v) <= COORDINATE_LIMIT for v in values):
        raise LinkError("cam", f"numbers must be finite and within ±{COORDINATE_LIMIT:g} m")
    position, look_at, up, fov = values[0:3], values[3:6], values[6:9], values[9]
    if math.dist(position, look_at) < 1e-9:
        raise LinkError("cam", "position and look-at point are the same")
    norm = math.hypot(*up)
    if norm < 1e-9:
        raise LinkError("cam", "the up vector is zero")
    if not 1.0 <= fov < 179.0:
        raise LinkError("cam", f"field of view must be 1-179 degrees (got {fov:g})")
    return {"position": position, "look_at": look_at, "up": [v / norm for v in up], "fov_deg": fov}


def parse_selection(raw: str | None) -> Selection | None:
    """``scan:K``, ``edge:I-J`` or ``loop:I-J`` (None or empty: nothing selected); LinkError naming ``sel``."""
    if raw is None or raw == "":
        return None
    match = _SELECTION.match(raw)
    if match is None:
        raise LinkError("sel", f"must be scan:K, edge:I-J or loop:I-J (got {raw[:40]!r})")
    if match.group(1):
        return Selection("scan", int(match.group(2)))
    i, j = int(match.group(4)), int(match.group(5))
    if i == j:
        raise LinkError("sel", f"an {match.group(3)} joins two different scans")
    return Selection(match.group(3), *edge_key(i, j))


def _colour(raw: str | None) -> str | None:
    if raw is None or raw == "":
        return None
    if raw not in COLOUR_MODES:
        raise LinkError("colour", f"must be one of {', '.join(COLOUR_MODES)} (got {raw[:20]!r})")
    return raw


def resolve_link(state: SessionState, editor: Editor, link: Permalink) -> dict[str, Any]:
    """The link checked against the session: its revision exists, its selection is there at that revision.

    The answer is what the page restores: the revision (``old`` when it is not the head), the camera,
    the selection described (``describe_selection``) and the colour mode.
    """
    session = state.session
    head = session.revision
    revision = head if link.revision is None else link.revision
    if revision not in session.journal.revisions() and revision != head:
        last = max(session.journal.revisions(), default=0)
        raise LinkError("rev", f"this session has no revision {revision} (revisions are 0..{last})")
    selected = None if link.selection is None else describe_selection(state, editor, link.selection, revision)
    return {
        "revision": revision,
        "head": head,
        "old": revision != head,
        "camera": link.camera,
        "selection": selected,
        "colour": link.colour,
    }


def describe_selection(state: SessionState, editor: Editor, selection: Selection, revision: int) -> dict[str, Any]:
    """What the page's selection panel shows of a selected item at ``revision``; LinkError when it is not there."""
    session = state.session
    state.sequence()  # a new session's revision 0 is made by its first load (once, under the state's lock)
    poses = session.poses(revision)
    count = len(poses)
    described: dict[str, Any] = {"kind": selection.kind, "text": selection.text(), "i": selection.i, "j": selection.j}
    if selection.kind == "scan":
        if selection.i >= count:
            raise LinkError("sel", f"no scan {selection.i}; the session has scans 0..{count - 1}")
        names = [path.name for path in session.scan_files()]
        described["name"] = names[selection.i] if selection.i < len(names) else str(selection.i)
        described["position"] = [float(v) for v in poses[selection.i][:3, 3]]
        return described
    assert selection.j is not None
    if selection.j >= count:
        raise LinkError("sel", f"no scan {selection.j}; the session has scans 0..{count - 1}")
    ends = [[float(v) for v in poses[k][:3, 3]] for k in (selection.i, selection.j)]
    described["ends"] = ends
    described["length"] = math.dist(*ends)
    if selection.kind == "edge":
        edges = graph_edge_list(count, session.graph(revision))
        found = next((e for e in edges if tuple(edge_key(e["i"], e["j"])) == (selection.i, selection.j)), None)
        if found is None:
            raise LinkError("sel", f"revision {revision} has no edge {selection.i}-{selection.j}")
        described["edge_kind"] = found["kind"]
        return described
    loops = editor.loops.listed(state.session.id)
    found = next((h for h in loops if tuple(edge_key(h["i"], h["j"])) == (selection.i, selection.j)), None)
    if found is None:
        raise LinkError("sel", f"no loop hypothesis {selection.i}-{selection.j} under review")
    described.update({"k": found["k"], "status": found["status"]})
    return described


__all__ = [
    "LINK_PARAMETERS",
    "LinkError",
    "Permalink",
    "Selection",
    "describe_selection",
    "parse_link",
    "parse_selection",
    "resolve_link",
]
