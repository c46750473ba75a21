"""A viewer's websocket messages: its camera reaches the 3D view, its clicks and drags do not."""

from __future__ import annotations

import msgspec
from viser._messages import GuiUpdateMessage, TransformControlsUpdateMessage, ViewerCameraMessage

from app.tokens import Grant, Role
from app.view_roles import may_send, message_type


def grant(role: Role) -> Grant:
    return Grant("t", role, "corridor", role.name, "", None, False)


CAMERA = ViewerCameraMessage(
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


def encoded(message: dict) -> bytes:
    return msgspec.msgpack.encode(message)


def test_only_the_camera_of_a_viewer_or_reviewer_reaches_the_view() -> None:
    click = encoded(GuiUpdateMessage("button-id", {"value": True}).as_serializable_dict())
    drag = encoded(
        TransformControlsUpdateMessage(
            "/gizmo", wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0)
        ).as_serializable_dict()
    )
    assert message_type(encoded(CAMERA)) == "ViewerCameraMessage"
    for role in (Role.viewer, Role.reviewer):
        assert may_send(grant(role), encoded(CAMERA))
        assert not may_send(grant(role), click)
        assert not may_send(grant(role), drag)
        assert not may_send(grant(role), b"\xc1 not msgpack")
        assert not may_send(grant(role), "text frame")
    for role in (Role.editor, Role.owner):
        assert may_send(grant(role), click) and may_send(grant(role), drag)
