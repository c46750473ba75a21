"""What a browser below the editor role may tell the 3D view.

The 3D view's panels (relax, accept a loop, move a scan with the gizmo, keyframes) act on the
session through viser's websocket, not through REST, so the REST routes' roles do not cover them.
The websocket proxy therefore reads each message a browser sends (viser's client messages are
one msgpack map each, with the message class name under ``type``) and forwards, for a grant
below ``editor``, only what changes nobody's state but the sender's: its own camera. Clicks on
buttons, changed inputs, gizmo drags and scene clicks of a viewer or reviewer never reach viser;
reviewers decide loops in the page (REST), where their role is checked.

A *private* view (:mod:`app.view.revision_view`: each browser in a scene of its own, nothing to
edit) also takes the browser's clicks in the scene, whatever its role: there a click only picks a
scan for that browser's own selection.
"""

from __future__ import annotations

import msgspec

from app.tokens import Grant, Role

# Messages that only describe the sender's own view.
VIEW_ONLY_MESSAGES = frozenset({"ViewerCameraMessage"})
# ... and, on a private view, what only changes the sender's own scene.
PRIVATE_VIEW_MESSAGES = VIEW_ONLY_MESSAGES | {"ScenePointerMessage"}


def message_type(raw: bytes) -> str | None:
    """The viser message class a browser's websocket message carries, or None if it is not one."""
    try:
        decoded = msgspec.msgpack.decode(raw)
    except msgspec.DecodeError:
        return None
    kind = decoded.get("type") if isinstance(decoded, dict) else None
    return kind if isinstance(kind, str) else None


def may_send(grant: Grant, raw: bytes | str, private: bool = False) -> bool:
    """Whether the 3D view (``private``: a view of its own per browser) may receive this message from a
    browser acting with ``grant``."""
    if grant.role >= Role.editor:
        return True
    allowed = PRIVATE_VIEW_MESSAGES if private else VIEW_ONLY_MESSAGES
    return isinstance(raw, bytes) and message_type(raw) in allowed


__all__ = ["PRIVATE_VIEW_MESSAGES", "VIEW_ONLY_MESSAGES", "may_send", "message_type"]
