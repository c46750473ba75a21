"""Every reproducer of the hostile-input report, as a request from outside: refused with the right
status and a message, nothing stored, no 500, no file content in the answer."""

from __future__ import annotations

import io
import json
import os
import shutil
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from slam6d.geometry import euler_to_rotation, make_pose
from slam6d.session import Session
from tests.session_fixtures import corridor_session, write_corridor_scans

CORRIDOR = "/api/sessions/corridor"
SECRET = "root:x:0:0:SECRET-TOKEN:/root:/bin/bash\n"


@pytest.fixture
def sessions_dir(tmp_path: Path) -> Path:
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=400, engine={"voxel_size": 0.2})
    return root


@pytest.fixture
def client(sessions_dir: Path):
    with TestClient(
        create_app(sessions_dir, viewers=False, max_upload_mb=1),
        base_url="http://127.0.0.1",
        raise_server_exceptions=False,
    ) as c:
        yield c


def _revisions(client: TestClient) -> list[int]:
    return client.get(CORRIDOR).json()["revisions"]


# ------------------------------------------------------------------ server files


@pytest.mark.parametrize("fmt", ["csv", "xyz", "uos"])
def test_a_server_file_is_never_quoted(client: TestClient, tmp_path: Path, fmt: str) -> None:
    secret = tmp_path / "passwd"
    secret.write_text(SECRET * 3)
    created = client.post("/api/sessions", json={"name": "leak", "source": str(secret), "format": fmt})
    answers = [created.text]
    if created.status_code == 201:
        sid = created.json()["id"]
        answers += [client.get(f"/api/sessions/{sid}/poses").text, client.get(f"/api/sessions/{sid}/export/map").text]
    for answer in answers:
        assert "SECRET" not in answer and "root:x" not in answer, answer


def test_devices_and_fifos_are_refused_at_once(client: TestClient, tmp_path: Path) -> None:
    zero = client.post("/api/sessions", json={"name": "zero", "source": "/dev/zero", "format": "xyz"})
    assert zero.status_code == 422 and "not a regular file (a device)" in zero.json()["detail"]
    fifo = tmp_path / "scan.xyz"
    os.mkfifo(fifo)
    answer = client.post("/api/sessions", json={"name": "fifo", "source": str(fifo), "format": "xyz"})
    assert answer.status_code == 422 and "FIFO" in answer.json()["detail"]


# ------------------------------------------------------------------ uploads


def _zip(entries: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", method) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
    return out.getvalue()


def test_a_nested_zip_bomb_is_refused_while_streaming_and_leaves_nothing(client: TestClient, sessions_dir) -> None:
    inner = _zip({"zeros.3d": bytes(20 << 20)})
    bomb = _zip({"scans.zip": inner, "scan000.3d": b"1 2 3\n"})
    answer = client.post("/api/sessions/upload", data={"name": "bomb"}, files=[("files", ("b.zip", bomb))])
    assert answer.status_code == 422 and "nested archives are not accepted" in answer.json()["detail"]
    total = _zip({"scan000.3d": bytes(3 << 20)})  # 3 kB that expand past the 1 MiB upload limit
    answer = client.post("/api/sessions/upload", data={"name": "ratio"}, files=[("files", ("r.zip", total))])
    assert answer.status_code == 413, answer.text
    assert sorted(p.name for p in sessions_dir.iterdir()) == ["corridor"]


def test_a_zip_with_a_bad_crc_is_422(client: TestClient, tmp_path: Path, sessions_dir) -> None:
    data = bytearray(
        _zip({"scan000.3d": b"1 2 3\n4 5 6\n" * 10, "scan000.pose": b"0 0 0\n0 0 0\n"}, zipfile.ZIP_STORED)
    )
    at = data.index(b"4 5 6")
    data[at] = ord("7")
    answer = client.post("/api/sessions/upload", data={"name": "crc"}, files=[("files", ("c.zip", bytes(data)))])
    assert answer.status_code == 422 and "damaged" in answer.json()["detail"]
    assert sorted(p.name for p in sessions_dir.iterdir()) == ["corridor"]


# ------------------------------------------------------------------ poison data


def test_a_poisoned_keyframe_is_refused_and_the_path_stays_usable(client: TestClient) -> None:
    keyframe = {"position": [0, 0, 2], "orientation_wxyz": [1e200, 0, 0, 0]}
    for url, body in (
        (f"{CORRIDOR}/camera-path/keyframes", keyframe),
        (f"{CORRIDOR}/camera-path", {"keyframes": [keyframe]}),
    ):
        answer = client.request("POST" if url.endswith("keyframes") else "PUT", url, json=body)
        assert answer.status_code == 422 and "orientation_wxyz" in json.dumps(answer.json()), answer.text
    assert client.get(f"{CORRIDOR}/camera-path").json()["keyframes"] == []
    for bad in ([0, 0, 0, 0], [float("nan"), 0, 0, 1]):
        answer = client.post(f"{CORRIDOR}/camera-path/keyframes", content=json.dumps({"position": [0, 0, 2], "orientation_wxyz": bad}), headers={"content-type": "application/json"})  # fmt: skip
        assert answer.status_code == 422
    good = {"position": [0, 0, 2], "orientation_wxyz": [2, 0, 0, 0]}
    assert client.post(f"{CORRIDOR}/camera-path/keyframes", json=good).status_code == 201
    assert client.get(f"{CORRIDOR}/camera-path").json()["keyframes"][0]["orientation_wxyz"] == [1.0, 0.0, 0.0, 0.0]
    assert client.put(f"{CORRIDOR}/camera-path", json={"keyframes": []}).status_code == 200  # can always be cleared


def _rigid() -> list[list[float]]:
    return make_pose(euler_to_rotation(0.0, 0.0, 0.3), [1.0, 0.5, 0.0]).tolist()


NOT_POSES = {
    "zero": np.zeros((4, 4)).tolist(),
    "scaled": np.diag([1.5, 1.5, 1.5, 1.0]).tolist(),
    "sheared": [[1, 0.4, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    "reflection": np.diag([1.0, -1.0, 1.0, 1.0]).tolist(),
    "garbage bottom row": [*_rigid()[:3], [3, 1, 4, 1]],
    "huge translation": [[1, 0, 0, 1e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    "ragged": [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    "strings": [["1", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
}


@pytest.mark.parametrize("kind", sorted(NOT_POSES))
def test_a_pose_that_is_not_rigid_is_422_and_never_stored(client: TestClient, kind: str) -> None:
    before = _revisions(client)
    answer = client.post(f"{CORRIDOR}/scans/1/pose", json={"pose": NOT_POSES[kind]})
    assert answer.status_code == 422, answer.text
    assert any("pose" in [str(p) for p in issue["loc"]] for issue in answer.json()["detail"])
    assert _revisions(client) == before


# ------------------------------------------------------------------ plain mistakes


def test_plain_mistakes_are_4xx_never_500(client: TestClient) -> None:
    assert client.get(f"{CORRIDOR}/poses", params={"rev": "9223372036854775808"}).status_code == 422
    assert client.get(f"{CORRIDOR}/poses", params={"rev": 2**31 - 2}).status_code == 404
    assert client.delete(f"{CORRIDOR}/edges/-1").status_code == 422
    surrogate = b'{"name": "\\ud800", "source": "/tmp"}'
    answer = client.post("/api/sessions", content=surrogate, headers={"content-type": "application/json"})
    assert answer.status_code == 422 and answer.json()["detail"][0]["loc"] == ["body", "name"]
    answer = client.post(f"{CORRIDOR}/jobs", json={"kind": "reload", "parameters": {"voxel_size": "abc"}})
    assert answer.status_code == 422 and "voxel_size" in answer.json()["detail"]
    assert client.post(f"{CORRIDOR}/render", json={"point_size": False}).status_code == 422
    assert client.post(f"{CORRIDOR}/render", json={"fps": "30"}).status_code == 422
    nan = b'{"position": [NaN, 0, 0], "orientation_wxyz": [1, 0, 0, 0]}'
    answer = client.post(f"{CORRIDOR}/camera-path/keyframes", content=nan, headers={"content-type": "application/json"})
    assert answer.status_code == 422


def test_a_30_mb_json_body_is_refused_before_it_is_parsed(client: TestClient) -> None:
    big = b'{"keyframes": [' + b'{"position": [0, 0, 0], "orientation_wxyz": [1, 0, 0, 0]},' * 520_000 + b"]}"
    assert len(big) > 30_000_000
    answer = client.put(f"{CORRIDOR}/camera-path", content=big, headers={"content-type": "application/json"})
    assert answer.status_code == 413 and "limit" in answer.json()["detail"]


def test_an_unexpected_error_is_500_with_a_reference_only(client: TestClient, monkeypatch) -> None:
    def broken(*args, **kwargs):
        raise RuntimeError("SECRET internal state")

    monkeypatch.setattr(Session, "scan_files", broken)
    answer = client.get(CORRIDOR)
    assert answer.status_code == 500
    assert "reference" in answer.json()["detail"] and "SECRET" not in answer.text


# ------------------------------------------------------------------ wrong answers


def test_redo_answers_the_revision_even_when_a_view_fails_to_follow(client: TestClient) -> None:
    moved = client.post(f"{CORRIDOR}/scans/1/pose", json={"pose": _rigid()})
    assert moved.status_code == 200, moved.text
    assert client.post(f"{CORRIDOR}/undo", json={}).status_code == 200

    def broken_view(session_id: str) -> None:
        raise ValueError("a view that cannot follow")

    client.app.state.workbench.on_revision(broken_view)  # type: ignore[attr-defined]
    redone = client.post(f"{CORRIDOR}/redo", json={})
    assert redone.status_code == 200 and redone.json()["revision"] == moved.json()["revision"]
    assert client.post(f"{CORRIDOR}/redo", json={}).status_code == 409  # now nothing is left to redo


def test_racing_first_reads_store_one_import(tmp_path: Path) -> None:
    write_corridor_scans(tmp_path / "s" / "scans", scans=3, points=300)
    Session.create(tmp_path / "s", "race", "scans")
    barrier = threading.Barrier(4)

    def first_read() -> None:
        session = Session.open(tmp_path / "s")  # each request opens its own, as two workers would
        barrier.wait()
        session.load_sequence()

    threads = [threading.Thread(target=first_read) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    entries = Session.open(tmp_path / "s").journal.entries()
    assert [e.kind for e in entries] == ["import"] and Session.open(tmp_path / "s").journal.revisions() == [0]


# ------------------------------------------------------------------ bundles over REST


def test_bundle_download_and_import_round_trip(client: TestClient, sessions_dir: Path) -> None:
    assert client.post(f"{CORRIDOR}/scans/2/pose", json={"pose": _rigid()}).status_code == 200
    bundle = client.get(f"{CORRIDOR}/bundle", params={"scans": "true"})
    assert bundle.status_code == 200 and bundle.headers["content-type"] == "application/zip"
    imported = client.post("/api/sessions/import", files={"file": ("corridor.zip", bundle.content)})
    assert imported.status_code == 201, imported.text
    copy = imported.json()["id"]
    assert copy != "corridor" and imported.json()["revision"] == client.get(CORRIDOR).json()["revision"]
    assert client.get(f"/api/sessions/{copy}/poses").text == client.get(f"{CORRIDOR}/poses").text
    evil = _zip({"../escape.txt": b"x"})
    assert client.post("/api/sessions/import", files={"file": ("e.zip", evil)}).status_code == 422
    assert sorted(p.name for p in sessions_dir.iterdir()) == sorted(["corridor", copy])


def test_a_bundle_without_scans_is_relinked_under_the_importing_servers_data_root(
    sessions_dir: Path, tmp_path: Path
) -> None:
    """Exported by one server without scans, imported by another holding the same scans under its own data
    root: re-linked after every hash is checked; the same bundle where a scan is missing is refused, naming
    it, with nothing written."""
    exporter = create_app(sessions_dir, viewers=False, data_root=sessions_dir / "corridor")
    with TestClient(exporter, base_url="http://127.0.0.1") as origin:
        assert origin.post(f"{CORRIDOR}/scans/2/pose", json={"pose": _rigid()}).status_code == 200
        bundle = origin.get(f"{CORRIDOR}/bundle").content
        poses = origin.get(f"{CORRIDOR}/poses").text
    other_data, other_sessions = tmp_path / "data", tmp_path / "team"
    shutil.copytree(sessions_dir / "corridor" / "scans", other_data / "scans")
    other_sessions.mkdir()
    importer = create_app(other_sessions, viewers=False, data_root=other_data)
    with TestClient(importer, base_url="http://127.0.0.1", raise_server_exceptions=False) as team:
        imported = team.post("/api/sessions/import", files={"file": ("c.zip", bundle)})
        assert imported.status_code == 201, imported.text
        copy = imported.json()["id"]
        assert team.get(f"/api/sessions/{copy}/poses").text == poses
        assert Session.open(other_sessions / copy).source_paths() == [(other_data / "scans").resolve()]

        (other_data / "scans" / "scan001.3d").unlink()
        refused = team.post("/api/sessions/import", files={"file": ("c.zip", bundle)})
        assert refused.status_code == 422
        assert "scan source 0" in refused.json()["detail"] and "missing scan001.3d" in refused.json()["detail"]
        assert sorted(p.name for p in other_sessions.iterdir() if not p.name.startswith(".")) == [copy]
