"""Private 3D views without a browser: the head in one's own colours follows every edit; their number is bounded."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app import errors
from app.server import create_app
from app.view import revision_view
from app.view.revision_view import RevisionViews
from tests.session_fixtures import corridor_session

SESSION = "/api/sessions/corridor"


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=400, engine={"voxel_size": 0.2})
    with TestClient(create_app(root, viewers=False), base_url="http://127.0.0.1") as c:
        yield c


@pytest.fixture
def views(client: TestClient) -> Iterator[RevisionViews]:
    opened = RevisionViews(client.app.state.workbench)  # type: ignore[attr-defined]
    yield opened
    opened.stop_all()


def _move(client: TestClient, scan: int, lift: float) -> tuple[int, np.ndarray]:
    pose = client.app.state.workbench.current_poses("corridor")[scan].copy()  # type: ignore[attr-defined]
    pose[2, 3] += lift
    moved = client.post(f"{SESSION}/scans/{scan}/pose", json={"pose": pose.tolist()})
    assert moved.status_code == 200, moved.text
    return int(moved.json()["revision"]), pose


def test_the_head_in_own_colours_follows_every_edit_and_an_old_revision_stays(
    client: TestClient, views: RevisionViews
) -> None:
    first = client.get(SESSION).json()["revision"]
    head = views.get("corridor", None)
    old = views.get("corridor", first)
    assert head.as_dict()["follows_head"] is True and old.as_dict()["follows_head"] is False
    assert views.get("corridor", None) is head  # one per session, shared by its browsers
    revision, pose = _move(client, 1, 1.5)
    assert revision != first
    assert head.as_dict()["revision_shown"] == revision
    assert np.allclose(head.as_dict()["positions"][1], pose[:3, 3], atol=1e-9)
    assert f"· revision {revision}**" in head.status.content
    assert old.as_dict()["revision_shown"] == first
    assert not np.allclose(old.as_dict()["positions"][1], pose[:3, 3], atol=1.0)


def test_private_views_are_bounded_with_a_message_saying_when_one_frees(
    client: TestClient, views: RevisionViews, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(revision_view, "MAX_VIEWS", 1)
    first = client.get(SESSION).json()["revision"]
    views.get("corridor", None)
    with pytest.raises(errors.EditError) as refused:
        views.get("corridor", first)
    assert refused.value.status == 409
    assert str(refused.value).startswith("1 private 3D views (older revisions, or the current one in a browser's own")
    assert "2 minutes after its last browser leaves" in str(refused.value)
