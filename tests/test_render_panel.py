"""Fly-through renders through the workbench's REST API, and `slam6d render` on a session folder."""

from __future__ import annotations

import json
import time

import imageio_ffmpeg
import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from app.server import create_app
from slam6d.cli import app as cli_app
from slam6d.session import Session
from tests.session_fixtures import corridor_session

# Two views down the corridor (x along it, z up), as a browser would send them.
VIEW_A = {"position": [0.0, 0.0, 1.5], "look_at": [10.0, 0.0, 1.0], "fov_deg": 60.0}
VIEW_B = {"position": [8.0, 0.5, 1.5], "look_at": [20.0, 0.0, 1.0], "fov_deg": 50.0}


@pytest.fixture
def sessions_dir(tmp_path):
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=600, engine={"voxel_size": 0.2})
    return root


@pytest.fixture
def client(sessions_dir):
    with TestClient(create_app(sessions_dir, viewers=False), base_url="http://127.0.0.1") as c:
        yield c


def wait_job(client, job_id: str, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/api/jobs/{job_id}").json()
        if job["status"] not in ("queued", "running"):
            return job
        assert time.monotonic() < deadline, f"job still {job['status']} after {timeout} s"
        time.sleep(0.05)


def positions(path: dict) -> list[list[float]]:
    return [k["position"] for k in path["keyframes"]]


def test_keyframes_are_added_reordered_deleted_and_saved_in_the_session(client, sessions_dir):
    assert client.get("/api/sessions/corridor/camera-path").json() == {
        "keyframes": [],
        "duration": 0.0,
        "default": True,
    }
    first = client.post("/api/sessions/corridor/camera-path/keyframes", json=VIEW_A, headers={"X-Author": "ana"})
    assert first.status_code == 201
    quaternion = first.json()["keyframes"][0]["orientation_wxyz"]
    # the same view again, given as a quaternion (what the browser's camera reports), inserted in front
    view_c = {"position": [4.0, -0.5, 1.2], "orientation_wxyz": quaternion, "fov_deg": 70.0, "index": 0}
    client.post("/api/sessions/corridor/camera-path/keyframes", json=VIEW_B)
    path = client.post("/api/sessions/corridor/camera-path/keyframes", json=view_c).json()
    assert positions(path) == [view_c["position"], VIEW_A["position"], VIEW_B["position"]]
    assert path["default"] is False and path["duration"] > 0
    # looking from VIEW_A towards its target: the camera's z axis (3rd column) points along +x, slightly down
    w, x, y, z = quaternion
    forward = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    expected = np.subtract(VIEW_A["look_at"], VIEW_A["position"])
    assert np.allclose(forward, expected / np.linalg.norm(expected), atol=1e-9)

    moved = client.post("/api/sessions/corridor/camera-path/keyframes/0/move", json={"to": 2}).json()
    assert positions(moved) == [VIEW_A["position"], VIEW_B["position"], view_c["position"]]
    after_delete = client.delete("/api/sessions/corridor/camera-path/keyframes/1", headers={"X-Author": "bob"}).json()
    assert positions(after_delete) == [VIEW_A["position"], view_c["position"]]
    assert [k["fov_deg"] for k in after_delete["keyframes"]] == [60.0, 70.0]

    # saved in the session itself: a fresh Session object (another process) reads the same keyframes
    saved = Session.open(sessions_dir / "corridor").camera_path()
    assert [k["position"] for k in saved] == positions(after_delete)
    entry = Session.open(sessions_dir / "corridor").journal.entries()[-1]
    assert (entry.kind, entry.author) == ("camera_path", "bob")

    cleared = client.put("/api/sessions/corridor/camera-path", json={"keyframes": []}).json()
    assert cleared["default"] is True and Session.open(sessions_dir / "corridor").camera_path() == []


@pytest.mark.parametrize(
    ("method", "url", "body", "status"),
    [
        ("post", "/api/sessions/nope/camera-path/keyframes", VIEW_A, 404),
        ("post", "/api/sessions/corridor/camera-path/keyframes", {"position": [0, 0, 0]}, 422),
        ("post", "/api/sessions/corridor/camera-path/keyframes", {**VIEW_A, "orientation_wxyz": [1, 0, 0, 0]}, 422),
        ("post", "/api/sessions/corridor/camera-path/keyframes", {**VIEW_A, "fov_deg": 200.0}, 422),
        ("post", "/api/sessions/corridor/camera-path/keyframes", {**VIEW_A, "look_at": VIEW_A["position"]}, 422),
        ("post", "/api/sessions/corridor/camera-path/keyframes", {"position": [0, 0], "look_at": [1, 0, 0]}, 422),
        ("post", "/api/sessions/corridor/camera-path/keyframes", {**VIEW_A, "index": 5}, 404),
        ("post", "/api/sessions/corridor/camera-path/keyframes/3/move", {"to": 0}, 404),
        ("post", "/api/sessions/corridor/camera-path/keyframes/0/move", {"to": -1}, 422),
        ("delete", "/api/sessions/corridor/camera-path/keyframes/7", None, 404),
        ("post", "/api/sessions/corridor/render", {"width": 321, "height": 240}, 422),
        ("post", "/api/sessions/corridor/render", {"color": "rainbow"}, 422),
        ("post", "/api/sessions/corridor/render", {"frames": 0}, 422),
        ("post", "/api/sessions/corridor/render", {"name": "../escape.mp4"}, 422),
        ("post", "/api/sessions/corridor/render", {"name": "clip.avi"}, 422),
        ("post", "/api/sessions/nope/render", {}, 404),
        ("get", "/api/sessions/corridor/renders/missing.mp4", None, 404),
        ("get", "/api/sessions/corridor/renders/session.toml", None, 404),
    ],
)
def test_bad_requests_are_refused(client, method, url, body, status):
    client.post("/api/sessions/corridor/camera-path/keyframes", json=VIEW_B)  # one keyframe exists
    response = client.request(method, url, json=body)
    assert response.status_code == status, response.text
    assert client.get("/api/sessions/corridor/renders").json() == []


def test_render_job_makes_a_downloadable_video_along_the_saved_keyframes(client, sessions_dir):
    for view in (VIEW_A, VIEW_B):
        client.post("/api/sessions/corridor/camera-path/keyframes", json=view)
    request = {"width": 96, "height": 64, "fps": 10, "frames": 6, "name": "clip.mp4"}
    started = client.post("/api/sessions/corridor/render", json=request, headers={"X-Author": "ana"})
    assert started.status_code == 202
    job = wait_job(client, started.json()["id"])
    assert job["status"] == "done", job["message"]
    assert job["kind"] == "render" and job["author"] == "ana" and job["done"] == job["total"] == 6
    assert job["result"]["path"] == "keyframes" and job["result"]["url"] == "/api/sessions/corridor/renders/clip.mp4"

    listed = client.get("/api/sessions/corridor/renders").json()
    assert [r["name"] for r in listed] == ["clip.mp4"] and listed[0]["bytes"] > 0
    download = client.get(job["result"]["url"])
    assert download.status_code == 200 and download.headers["content-type"] == "video/mp4"
    assert 'filename="clip.mp4"' in download.headers["content-disposition"]
    assert download.content[4:8] == b"ftyp"
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(sessions_dir / "corridor" / "renders" / "clip.mp4"))
    assert frames == 6
    # the same name again is refused rather than overwritten
    assert client.post("/api/sessions/corridor/render", json=request).status_code == 409


def test_render_without_keyframes_follows_the_trajectory(client):
    job = wait_job(client, client.post("/api/sessions/corridor/render", json={"width": 64, "height": 48}).json()["id"])
    assert job["status"] == "done", job["message"]
    assert job["result"]["path"] == "trajectory" and job["result"]["frames"] > 1
    assert job["result"]["name"].endswith(".mp4")
    assert client.get(job["result"]["url"]).status_code == 200


def test_cancelled_render_leaves_no_file(client, sessions_dir):
    for view in (VIEW_A, VIEW_B):
        client.post("/api/sessions/corridor/camera-path/keyframes", json=view)
    started = client.post("/api/sessions/corridor/render", json={"width": 64, "height": 48, "frames": 20_000})
    job_id = started.json()["id"]
    deadline = time.monotonic() + 30
    while client.get(f"/api/jobs/{job_id}").json()["done"] < 3:  # cancel in the middle of rendering
        assert time.monotonic() < deadline, "render made no progress"
        time.sleep(0.02)
    queued = client.post("/api/sessions/corridor/render", json={"width": 64, "height": 48})
    assert queued.status_code == 202 and queued.json()["status"] == "queued"  # one render at a time per session
    client.delete(f"/api/jobs/{queued.json()['id']}")
    client.delete(f"/api/jobs/{job_id}")
    job = wait_job(client, job_id)
    assert job["status"] == "cancelled" and 3 <= job["done"] < 20_000
    renders = sessions_dir / "corridor" / "renders"
    assert list(renders.iterdir()) == []  # not even the hidden partial file
    assert client.get("/api/sessions/corridor/renders").json() == []


def test_cli_renders_a_session_along_its_saved_path(sessions_dir, tmp_path):
    session = Session.open(sessions_dir / "corridor")
    keyframes = [
        {"position": [0.0, 0.0, 1.5], "orientation_wxyz": [0.5, -0.5, 0.5, -0.5], "fov_deg": 60.0},
        {"position": [6.0, 0.0, 1.5], "orientation_wxyz": [0.5, -0.5, 0.5, -0.5], "fov_deg": 60.0},
    ]
    session.set_camera_path(keyframes, "ana")
    out, used = tmp_path / "fly.mp4", tmp_path / "used.json"
    result = CliRunner().invoke(
        cli_app,
        ["render", str(session.folder), "-o", str(out), "--size", "80x60", "--frames", "5", "--save-path", str(used)],
    )
    assert result.exit_code == 0, result.output
    assert imageio_ffmpeg.count_frames_and_secs(str(out))[0] == 5
    saved = json.loads(used.read_text())["keyframes"]
    assert [k["position"] for k in saved] == [k["position"] for k in keyframes]
    assert np.allclose([k["orientation_wxyz"] for k in saved], [k["orientation_wxyz"] for k in keyframes])


def test_a_dot_dot_render_name_reaches_the_download_guard_and_is_refused(client):
    """An encoded ``..`` is decoded before routing, so it arrives at the handler as the name itself: the
    answer is the handler's own refusal (naming it), not the router's "Not Found". (An encoded slash
    never reaches it: a name holds no "/", so ``..%2Fsession.toml`` cannot even match the route.)"""
    for encoded in ("%2E%2E", ".%2E", "..%5Csession.toml"):
        response = client.get(f"/api/sessions/corridor/renders/{encoded}")
        assert response.status_code == 404
        assert response.json()["detail"].startswith("no render '..")
