"""A viewer's websocket messages: its camera reaches the 3D view, its clicks and drags do not (on a private
view its clicks in the scene do: there they only pick for the viewer's own selection)."""

from __future__ import annotations

from viser._messages import GuiUpdateMessage, ScenePointerMessage, TransformControlsUpdateMessage

from app.tokens import Grant, Role
from app.view_roles import may_send, message_type
from tests.viser_protocol import CAMERA, encoded


def grant(role: Role) -> Grant:
    return Grant("t", role, "corridor", role.name, "", None, False)


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


def test_a_private_view_takes_a_viewers_clicks_in_the_scene_and_nothing_else() -> None:
    scene_click = encoded(
        ScenePointerMessage("click", (0.0, 0.0, 5.0), (0.0, 0.0, -1.0), ((0.5, 0.5),), None).as_serializable_dict()
    )
    button = encoded(GuiUpdateMessage("button-id", {"value": True}).as_serializable_dict())
    for role in (Role.viewer, Role.reviewer):
        assert not may_send(grant(role), scene_click)  # the shared view: a click there picks for edits
        assert may_send(grant(role), scene_click, private=True)
        assert may_send(grant(role), encoded(CAMERA), private=True)
        assert not may_send(grant(role), button, private=True)
