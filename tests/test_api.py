"""REST API of the workbench: listing, details, poses per revision, exports, uploads, jobs, errors."""

from __future__ import annotations

import io
import zipfile

import laspy
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from slam6d.errors import Cancelled
from slam6d.io.map import write_map
from slam6d.io.ply import read_ply
from tests.session_fixtures import corridor_session, true_poses, write_corridor_scans


@pytest.fixture
def sessions_dir(tmp_path):
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=400, engine={"voxel_size": 0.2})
    return root


@pytest.fixture
def client(sessions_dir):
    with TestClient(create_app(sessions_dir, viewers=False, max_upload_mb=1), base_url="http://127.0.0.1") as c:
        yield c


def scan_bytes(tmp_path, scans=2, points=200, seed=3) -> list[tuple[str, bytes]]:
    folder = tmp_path / f"upload-{seed}"
    write_corridor_scans(folder, scans=scans, points=points, seed=seed)
    return [(p.name, p.read_bytes()) for p in sorted(folder.iterdir())]


def kitti(text: str) -> list[np.ndarray]:
    rows = np.array([[float(v) for v in line.split()] for line in text.strip().splitlines()])
    return [np.vstack([r.reshape(3, 4), [0, 0, 0, 1]]) for r in rows]


def test_list_and_details(client):
    listed = client.get("/api/sessions").json()
    assert listed == [
        {
            "id": "corridor",
            "name": "Corridor",
            "scans": 3,
            "revision": 0,
            "format": "uos",
            "error": None,
            "repaired": [],
        }
    ]
    details = client.get("/api/sessions/corridor").json()
    assert details["scan_files"] == ["scan000.3d", "scan001.3d", "scan002.3d"]
    assert details["config"]["frame"] == "uos" and details["config"]["metres_per_unit"] == 0.01
    assert details["can_undo"] is False


def test_poses_are_kitti_lines_in_the_canonical_frame(client):
    response = client.get("/api/sessions/corridor/poses")
    assert response.status_code == 200 and response.headers["x-revision"] == "0"
    for got, expected in zip(kitti(response.text), true_poses(3), strict=True):
        assert np.allclose(got, expected, atol=1e-4)
    native = kitti(client.get("/api/sessions/corridor/poses?frame=native").text)
    assert np.allclose(native[1][:3, 3], [-10 * np.sin(1), 0.0, 200.0], atol=1e-2)  # cm, y up, z forward


def test_undo_redo_over_rest_changes_served_poses(client, sessions_dir):
    app_state = client.app.state.workbench
    poses = app_state.current_poses("corridor")
    poses[1] = poses[1].copy()
    poses[1][2, 3] += 0.5
    assert app_state.commit("corridor", poses, "ana", "manual_move", {"scan": 1}) == 1
    assert kitti(client.get("/api/sessions/corridor/poses").text)[1][2, 3] == pytest.approx(0.5, abs=1e-6)
    assert client.post("/api/sessions/corridor/undo", json={}, headers={"X-Author": "bob"}).json() == {"revision": 0}
    assert kitti(client.get("/api/sessions/corridor/poses").text)[1][2, 3] == pytest.approx(0.0, abs=1e-6)
    assert kitti(client.get("/api/sessions/corridor/poses?rev=1").text)[1][2, 3] == pytest.approx(0.5, abs=1e-6)
    assert client.post("/api/sessions/corridor/redo", json={}).json() == {"revision": 1}
    journal = client.get("/api/sessions/corridor/journal").json()
    assert [(e["kind"], e["author"]) for e in journal] == [
        ("import", "system"),
        ("manual_move", "ana"),
        ("undo", "bob"),
        ("redo", "anonymous"),
    ]
    response = client.post("/api/sessions/corridor/redo", json={})
    assert response.status_code == 409 and "nothing to redo" in response.json()["detail"]


def test_pose_exports(client):
    tum = client.get("/api/sessions/corridor/export/poses?format=tum")
    assert tum.status_code == 200 and "attachment" in tum.headers["content-disposition"]
    assert len(tum.text.strip().splitlines()) == 3 and len(tum.text.split("\n")[0].split()) == 8
    g2o = client.get("/api/sessions/corridor/export/poses?format=g2o").text
    assert g2o.count("VERTEX_SE3:QUAT") == 3 and g2o.count("EDGE_SE3:QUAT") == 2 and "FIX 0" in g2o
    frames = client.get("/api/sessions/corridor/export/poses?format=frames")
    names = zipfile.ZipFile(io.BytesIO(frames.content)).namelist()
    assert sorted(names) == ["scan000.frames", "scan001.frames", "scan002.frames"]
    line = zipfile.ZipFile(io.BytesIO(frames.content)).read("scan001.frames").decode().split()
    assert len(line) == 17 and float(line[14]) == pytest.approx(200.0, abs=0.01)  # z_uos (forward) in cm


def test_map_exports_ply_and_laz(client, tmp_path):
    ply = client.get("/api/sessions/corridor/export/map?format=ply")
    assert ply.status_code == 200
    (tmp_path / "map.ply").write_bytes(ply.content)
    points = read_ply(tmp_path / "map.ply").points
    assert len(points) == 1200
    assert points[:, 2].min() == pytest.approx(0.0, abs=0.01) and points[:, 0].max() < 22.1
    laz = client.get("/api/sessions/corridor/export/map?format=laz&voxel=0.5")
    (tmp_path / "map.laz").write_bytes(laz.content)
    las = laspy.read(tmp_path / "map.laz")
    assert 50 < len(las.points) < 1200
    assert float(np.min(las.z)) == pytest.approx(0.0, abs=0.01)


def test_map_downloads_are_the_engine_writers_bytes(client, tmp_path):
    """The merged map a user downloads is byte for byte what slam6d.io.map.write_map writes for those points."""
    sequence = client.app.state.workbench.state("corridor").sequence()
    points = np.concatenate([s.points @ s.pose[:3, :3].T + s.pose[:3, 3] for s in sequence.scans])
    for fmt in ("ply", "laz"):
        reference = write_map(tmp_path / f"reference.{fmt}", points)
        download = client.get(f"/api/sessions/corridor/export/map?format={fmt}")
        assert download.status_code == 200
        assert download.content == reference.read_bytes(), fmt
    las = laspy.read(tmp_path / "reference.laz")
    assert np.allclose(las.header.scales, 1e-4)  # the engine's 0.1 mm, not a second writer's millimetre


def test_g2o_export_carries_each_edges_information_from_the_overlap(client):
    def edges(text: str) -> list[np.ndarray]:
        rows, cols = np.triu_indices(6)
        infos = []
        for line in text.splitlines():
            if line.startswith("EDGE_SE3:QUAT"):
                info = np.zeros((6, 6))
                info[rows, cols] = [float(v) for v in line.split()[10:]]
                infos.append(info + np.triu(info, 1).T)
        return infos

    canonical = edges(client.get("/api/sessions/corridor/export/poses?format=g2o").text)
    assert len(canonical) == 2
    for info in canonical:
        assert not np.allclose(info, np.eye(6))  # measured, not a placeholder
        assert np.all(np.linalg.eigvalsh(info) > 0)  # the overlap pins every direction down
    native = edges(client.get("/api/sessions/corridor/export/poses?format=g2o&frame=native").text)
    convention = client.app.state.workbench.state("corridor").session.config.convention
    for a, b in zip(canonical, native, strict=True):
        np.testing.assert_allclose(convention.information_to_native(a), b, rtol=1e-6)


def test_unknown_ids_are_404(client):
    assert client.get("/api/sessions/nope").status_code == 404
    assert client.get("/api/sessions/nope/poses").status_code == 404
    # an encoded ".." arrives at the session lookup as the id itself and is refused there, by name
    traversal = client.get("/api/sessions/%2E%2E/poses")
    assert traversal.status_code == 404 and traversal.json()["detail"] == "no session '..'"
    assert client.get("/api/sessions/corridor/poses?rev=9").status_code == 404
    assert client.get("/api/jobs/job-999").status_code == 404
    assert client.delete("/api/jobs/job-999").status_code == 404
    assert client.get("/sessions/nope").status_code == 404


def test_bad_query_values_are_422(client):
    assert client.get("/api/sessions/corridor/export/poses?format=csv").status_code == 422
    assert client.get("/api/sessions/corridor/poses?rev=-1").status_code == 422
    assert client.get("/api/sessions/corridor/export/map?voxel=-2").status_code == 422


def test_create_from_folder(client, tmp_path, sessions_dir):
    write_corridor_scans(tmp_path / "more", scans=2, points=100)
    created = client.post("/api/sessions", json={"name": "More scans", "source": str(tmp_path / "more")})
    assert created.status_code == 201
    assert created.json()["id"] == "More-scans" and created.json()["scans"] == 2
    bad = client.post("/api/sessions", json={"name": "x", "source": str(tmp_path / "missing")})
    assert bad.status_code == 422 and "no such file" in bad.json()["detail"]
    (tmp_path / "empty").mkdir()
    bad = client.post("/api/sessions", json={"name": "y", "source": str(tmp_path / "empty"), "format": "uos"})
    assert bad.status_code == 422 and "no 'uos' scans" in bad.json()["detail"]
    assert sorted(p.name for p in sessions_dir.iterdir()) == ["More-scans", "corridor"]


def test_upload_creates_a_session_from_files_or_a_zip(client, tmp_path, sessions_dir):
    files = scan_bytes(tmp_path)
    response = client.post("/api/sessions/upload", data={"name": "Uploaded"}, files=[("files", f) for f in files])
    assert response.status_code == 201, response.text
    assert response.json()["scans"] == 2
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        for name, data in scan_bytes(tmp_path, seed=4):
            z.writestr(f"run1/{name}", data)
    response = client.post(
        "/api/sessions/upload", data={"name": "Zipped"}, files=[("files", ("scans.zip", archive.getvalue()))]
    )
    assert response.status_code == 201, response.text
    assert kitti(client.get(f"/api/sessions/{response.json()['id']}/poses").text)[1][0, 3] == pytest.approx(2.0, 1e-4)


@pytest.mark.parametrize(
    ("files", "status", "message"),
    [
        ([("files", ("scan000.3d", b"1 2 3\n4 5 oops\n"))], 422, "scan000.3d:2"),
        ([("files", ("../evil.3d", b"1 2 3\n"))], 422, "no 'uos' scans"),
        ([("files", ("bad name!.3d", b"1 2 3\n"))], 422, "not allowed"),
        ([("files", ("scans.zip", b"PK not a zip"))], 422, "not a valid zip"),
        ([("files", ("scan000.3d", b"1 2 3\n" * 300_000))], 413, "limit"),
    ],
)
def test_malformed_uploads_are_refused_and_leave_nothing(client, sessions_dir, files, status, message):
    before = sorted(p.name for p in sessions_dir.iterdir())
    response = client.post("/api/sessions/upload", data={"name": "Bad", "format": "uos"}, files=files)
    assert response.status_code == status, response.text
    assert message in response.json()["detail"]
    assert sorted(p.name for p in sessions_dir.iterdir()) == before


def test_zip_with_traversal_is_refused(client, sessions_dir):
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("../../scan000.3d", "1 2 3\n")
    response = client.post("/api/sessions/upload", data={"name": "Z"}, files=[("files", ("a.zip", archive.getvalue()))])
    assert response.status_code == 422 and "unsafe path" in response.json()["detail"]
    assert sorted(p.name for p in sessions_dir.iterdir()) == ["corridor"]


def test_upload_without_files_is_422(client):
    assert client.post("/api/sessions/upload", data={"name": "Nothing"}).status_code == 422


def test_jobs_report_progress_and_result(client):
    started = client.post("/api/sessions/corridor/jobs", json={"kind": "reload", "parameters": {"voxel_size": 0.5}})
    assert started.status_code == 202
    job = client.app.state.workbench.jobs.wait(started.json()["id"])
    state = client.get(f"/api/jobs/{job.id}").json()
    assert state["status"] == "done" and state["fraction"] == 1.0
    assert state["result"]["scans"] == 3 and state["result"]["points"] == 1200
    assert 0 < state["result"]["reduced"] < 1200
    assert client.post("/api/sessions/corridor/jobs", json={"kind": "dance"}).status_code == 422
    assert client.post("/api/sessions/nope/jobs", json={"kind": "reload"}).status_code == 404


def test_cancelling_a_job(client):
    workbench = client.app.state.workbench
    import threading

    gate = threading.Event()

    def work(progress, cancel):
        for k in range(1000):
            progress("waiting", k, 1000)
            gate.set()
            if cancel():
                raise Cancelled("stopped")
            threading.Event().wait(0.01)
        return {}

    job = workbench.jobs.submit("corridor", "test", work, "ana")
    gate.wait(5)
    waiting = client.post("/api/sessions/corridor/jobs", json={"kind": "register"})  # same lane: queued
    assert waiting.status_code == 202 and waiting.json()["status"] == "queued"
    assert client.delete(f"/api/jobs/{waiting.json()['id']}").json()["status"] == "cancelled"
    assert client.delete(f"/api/jobs/{job.id}").json()["cancel_requested"] is True
    assert workbench.jobs.wait(job.id).status == "cancelled"
    assert client.get(f"/api/jobs/{job.id}").json()["status"] == "cancelled"


def test_openapi_documents_the_api(client):
    schema = client.get("/openapi.json").json()
    for path in ("/api/sessions", "/api/sessions/{session_id}/poses", "/api/jobs/{job_id}"):
        assert path in schema["paths"]
    assert client.get("/docs").status_code == 200


def test_pages_are_served(client):
    assert "Sessions" in client.get("/").text
    assert "iframe" in client.get("/sessions/corridor").text
