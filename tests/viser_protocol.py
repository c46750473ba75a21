"""viser's wire messages as a browser sends them, for tests that speak to a 3D view without a page.

The camera message is the one a web page sends first; viser counts a connection as a client once
it arrives, and it is the only message a viewer's websocket lets through (:mod:`app.view_roles`).
"""

from __future__ import annotations

from typing import Any

import msgspec
from viser._messages import ViewerCameraMessage

CAMERA: dict[str, Any] = ViewerCameraMessage(
    position=(1.0, 2.0, 3.0),
    wxyz=(1.0, 0.0, 0.0, 0.0),
    fov=1.0,
    near=0.01,
    far=100.0,
    image_height=480,
    image_width=640,
    look_at=(0.0, 0.0, 0.0),
    up_direction=(0.0, 0.0, 1.0),
).as_serializable_dict()


def encoded(message: dict[str, Any]) -> bytes:
    """A message as it goes over the websocket (msgpack)."""
    return msgspec.msgpack.encode(message)
