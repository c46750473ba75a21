"""What a browser below the editor role may tell the 3D view.

The 3D view's panels (relax, accept a loop, move a scan with the gizmo, keyframes) act on the
session through viser's websocket, not through REST, so the REST routes' roles do not cover them.
The websocket proxy therefore reads each message a browser sends (viser's client messages are
one msgpack map each, with the message class name under ``type``) and forwards, for a grant
below ``editor``, only what changes nobody's state but the sender's: its own camera. Clicks on
buttons, changed inputs, gizmo drags and scene clicks of a viewer or reviewer never reach viser;
reviewers decide loops in the page (REST), where their role is checked.
"""

from __future__ import annotations

import msgspec

from app.tokens import Grant, Role

# Messages that only describe the sender's own view.
VIEW_ONLY_MESSAGES = frozenset({"ViewerCameraMessage"})


def message_type(raw: bytes) -> str | None:
    """The viser message class a browser's websocket message carries, or None if it is not one."""
    try:
        decoded = msgspec.msgpack.decode(raw)
    except msgspec.DecodeError:
        return None
    kind = decoded.get("type") if isinstance(decoded, dict) else None
    return kind if isinstance(kind, str) else None


def may_send(grant: Grant, raw: bytes | str) -> bool:
    """Whether the 3D view may receive this message from a browser acting with ``grant``."""
    if grant.role >= Role.editor:
        return True
    return isinstance(raw, bytes) and message_type(raw) in VIEW_ONLY_MESSAGES


__all__ = ["VIEW_ONLY_MESSAGES", "may_send", "message_type"]
