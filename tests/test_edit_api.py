"""Editing over REST: loop review, edges by hand, moves with residual guardrails, loop closing,
relaxation (and its refusals), octree candidates, stored run traces and their replay."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.server import create_app
from app.traces import replay_frames
from slam6d.geometry import invert, pose_difference
from slam6d.session import Session
from tests.session_fixtures import corridor_session, true_poses, write_loop_scans

CORRIDOR = "/api/sessions/corridor"
LOOP = "/api/sessions/loop"


@pytest.fixture(scope="module")
def loop_scans(tmp_path_factory):
    """The simulated loop's scan files, written once (sessions over them are cheap)."""
    folder = tmp_path_factory.mktemp("loop-scans")
    truth = write_loop_scans(folder, points=20000)  # 6,000 points per scan leave the 0-7 loop ambiguous
    return folder, truth


@pytest.fixture
def client(tmp_path, loop_scans):
    root = tmp_path / "sessions"
    corridor_session(root, scans=4, points=3000, odometry_noise=0.1, engine={"voxel_size": 0.1})
    Session.create(root / "loop", "Loop", loop_scans[0])
    with TestClient(create_app(root, viewers=False)) as c:
        yield c


def wait(client, response, status="done"):  # type: ignore[no-untyped-def]
    assert response.status_code == 202, response.text
    job = client.app.state.workbench.jobs.wait(response.json()["id"], timeout=120)
    assert job.status == status, job.message
    return job


def poses_of(client, session: str) -> list[np.ndarray]:  # type: ignore[no-untyped-def]
    return client.app.state.workbench.current_poses(session)


def revision(client, base: str) -> int:  # type: ignore[no-untyped-def]
    return client.get(base).json()["revision"]


def test_loop_hypotheses_are_reviewed_accepted_rejected_and_undone(client):
    wait(client, client.post(f"{LOOP}/loops/detect", headers={"X-Author": "ana"}))
    listed = client.get(f"{LOOP}/loops").json()
    loop = next(h for h in listed if (h["i"], h["j"]) == (0, 7))
    assert loop["status"] == "pending" and loop["verified"] and loop["overlap"] > 0.2 and loop["fitness"] > 0.3
    assert loop["distance"] < 2.0 and loop["transform"] is not None
    k = loop["k"]

    accepted = client.post(f"{LOOP}/loops/{k}/accept", headers={"X-Author": "ana"})
    assert accepted.status_code == 200, accepted.text
    assert accepted.json()["revision"] == 1 and revision(client, LOOP) == 1
    assert client.get(f"{LOOP}/loops").json()[k]["status"] == "accepted"
    edges = client.get(f"{LOOP}/edges").json()
    assert any(e["kind"] == "loop" and (e["i"], e["j"]) == (0, 7) for e in edges)
    assert client.post(f"{LOOP}/loops/{k}/accept").status_code == 409  # already accepted

    rejected = client.post(f"{LOOP}/loops/{k}/reject", headers={"X-Author": "bob"})
    assert rejected.json()["revision"] == 2
    assert client.get(f"{LOOP}/loops").json()[k]["status"] == "rejected"
    assert not any(e["kind"] == "loop" for e in client.get(f"{LOOP}/edges").json())

    assert client.post(f"{LOOP}/undo").json() == {"revision": 1}
    assert client.get(f"{LOOP}/loops").json()[k]["status"] == "accepted"
    kinds = [(e["kind"], e["author"]) for e in client.get(f"{LOOP}/journal").json()]
    assert ("accept_loop", "ana") in kinds and ("reject_loop", "bob") in kinds
    assert client.post(f"{LOOP}/loops/99/accept").status_code == 404


def drift(poses: list[np.ndarray]) -> list[np.ndarray]:
    """Odometry-like drift growing along the path: a yaw and a sideways slip about scan 0."""
    from slam6d.geometry import pose_from_xyzrpy

    return [pose_from_xyzrpy(0.0, 0.05 * k, 0.0, 0.0, 0.0, 0.02 * k) @ p for k, p in enumerate(poses)]


def test_a_manual_loop_edge_then_loop_closing_and_lum_remove_drift(client):
    truth = true_poses(4)
    workbench = client.app.state.workbench
    workbench.state("corridor").sequence()  # revision 0: the files' poses
    workbench.commit("corridor", drift(truth), "sim", "manual_move", {"drift": True})

    def end_error() -> float:
        poses = poses_of(client, "corridor")
        return pose_difference(invert(poses[0]) @ poses[3], invert(truth[0]) @ truth[3])[0]

    drifted = end_error()
    assert client.post(f"{CORRIDOR}/edges", json={"i": 0, "j": 3}).status_code == 201
    job = wait(client, client.post(f"{CORRIDOR}/close-loops", headers={"X-Author": "ana"}))
    closed = end_error()
    assert drifted > 0.3 and closed < 0.05, (drifted, closed)
    assert job.result["revision"] == 3 and len(job.result["residual_after"]["edges"]) == 4
    assert job.result["residual_after"]["rms"] < job.result["residual_before"]["rms"]
    entry = [e for e in client.get(f"{CORRIDOR}/journal").json() if e["kind"] != "job"][-1]  # not the job's record
    assert (entry["kind"], entry["author"]) == ("close_loops", "ana")
    assert len(entry["parameters"]["displacement"]) == 4 and entry["parameters"]["displacement"][0] == 0.0
    moved = client.get(f"{CORRIDOR}/displacement?before=2").json()["displacement"]
    assert moved[0] == pytest.approx(0.0) and moved[3] > 0.2 and moved[1] < moved[3]

    job = wait(client, client.post(f"{CORRIDOR}/relax", json={"method": "lum", "fixed": [0]}))
    assert job.result["revision"] == 4
    assert job.result["residual_after"]["rms"] <= job.result["residual_before"]["rms"] + 1e-3
    poses = poses_of(client, "corridor")
    for k in range(1, 4):
        assert pose_difference(invert(poses[0]) @ poses[k], invert(truth[0]) @ truth[k])[0] < 0.03


def test_adding_an_edge_is_an_icp_refined_revision_and_undo_removes_it(client):
    added = client.post(f"{CORRIDOR}/edges", json={"i": 2, "j": 0}, headers={"X-Author": "carla"})
    assert added.status_code == 201, added.text
    body = added.json()
    assert (
        body["revision"] == 1 and body["edge"]["kind"] == "manual" and (body["edge"]["i"], body["edge"]["j"]) == (0, 2)
    )
    truth = true_poses(4)
    expected = invert(truth[0]) @ truth[2]
    metres, radians = pose_difference(np.array(body["edge"]["transform"]), expected)
    assert metres < 0.05 and radians < 0.01  # ICP found the true relative pose despite 10 cm odometry noise
    assert [(e["i"], e["j"], e["kind"]) for e in client.get(f"{CORRIDOR}/edges").json()][-1] == (0, 2, "manual")
    assert client.post(f"{CORRIDOR}/undo").json() == {"revision": 0}
    assert all(e["kind"] == "sequential" for e in client.get(f"{CORRIDOR}/edges").json())
    assert client.post(f"{CORRIDOR}/redo").json() == {"revision": 1}
    assert client.post(f"{CORRIDOR}/edges", json={"i": 1, "j": 1}).status_code == 422
    assert client.post(f"{CORRIDOR}/edges", json={"i": 1, "j": 9}).status_code == 404


def test_deleting_an_edge_disconnects_the_graph_and_relaxation_says_why(client):
    edges = client.get(f"{CORRIDOR}/edges").json()
    k = next(e["k"] for e in edges if (e["i"], e["j"]) == (1, 2))
    deleted = client.delete(f"{CORRIDOR}/edges/{k}", headers={"X-Author": "dan"})
    assert deleted.json()["revision"] == 1 and deleted.json()["deleted"] == {"i": 1, "j": 2, "kind": "sequential"}
    assert [(e["i"], e["j"]) for e in client.get(f"{CORRIDOR}/edges").json()] == [(0, 1), (2, 3)]

    refused = client.post(f"{CORRIDOR}/relax", json={"method": "graph", "fixed": [0]})
    assert refused.status_code == 409
    assert "disconnected" in refused.json()["detail"] and "(2, 3)" in refused.json()["detail"]
    no_fixed = client.post(f"{CORRIDOR}/relax", json={"method": "graph", "fixed": []})
    assert no_fixed.status_code == 409 and "no fixed scan" in no_fixed.json()["detail"]
    assert client.post(f"{CORRIDOR}/relax", json={"method": "magic"}).status_code == 422
    assert client.get("/api/jobs/job-1").status_code == 404  # nothing was started
    assert client.delete(f"{CORRIDOR}/edges/42").status_code == 404

    client.post(f"{CORRIDOR}/undo")
    job = wait(client, client.post(f"{CORRIDOR}/relax", json={"method": "graph", "fixed": [0]}))
    truth = true_poses(4)
    poses = poses_of(client, "corridor")
    for k in range(1, 4):  # odometry noise of 10 cm is gone: scans sit where the truth has them
        assert pose_difference(invert(poses[0]) @ poses[k], invert(truth[0]) @ truth[k])[0] < 0.03
    assert job.result["warning"] is None


def test_a_move_that_makes_residuals_jump_is_warned_about(client):
    poses = poses_of(client, "corridor")
    far = poses[2].copy()
    far[:3, 3] += [0.0, 1.5, 0.8]
    moved = client.post(f"{CORRIDOR}/scans/2/pose", json={"pose": far.tolist()}, headers={"X-Author": "eve"})
    assert moved.status_code == 200, moved.text
    body = moved.json()
    assert body["revision"] == 1 and body["warning"] and "residuals jumped" in body["warning"]
    assert body["residual_after"]["rms"] > body["residual_before"]["rms"]
    entry = client.get(f"{CORRIDOR}/journal").json()[-1]
    assert entry["kind"] == "manual_move" and entry["author"] == "eve" and "warning" in entry["parameters"]
    assert np.allclose(poses_of(client, "corridor")[2], far)

    nudge = poses_of(client, "corridor")[1].copy()
    nudge[0, 3] += 0.01
    assert client.post(f"{CORRIDOR}/scans/1/pose", json={"pose": nudge.tolist()}).json()["warning"] is None
    bad = client.post(f"{CORRIDOR}/scans/1/pose", json={"pose": [[1, 0, 0]]})
    assert bad.status_code == 422


def test_icp_from_a_dragged_place_snaps_the_scan_back(client):
    truth = true_poses(4)
    start = truth[3].copy()
    start[:3, 3] += [0.15, -0.12, 0.0]
    body = client.post(f"{CORRIDOR}/scans/3/pose", json={"pose": start.tolist(), "refine": True}).json()
    assert body["revision"] == 1 and body["warning"] is None
    got = poses_of(client, "corridor")[3]
    # relative to its graph neighbour (scan 2, at its odometry pose) the scan is where the truth says
    neighbour = poses_of(client, "corridor")[2]
    assert pose_difference(invert(neighbour) @ got, invert(truth[2]) @ truth[3])[0] < 0.05


def test_octree_guess_lists_ranked_candidates_and_runs_icp_from_one(client):
    response = client.get(f"{CORRIDOR}/guess?data=2&top=8")
    assert response.status_code == 200, response.text
    guess = response.json()
    assert guess["model"] == 1 and guess["data"] == 2 and guess["model_cubes"] > 100 and guess["data_cubes"] > 100
    scores = [c["score"] for c in guess["candidates"]]
    assert len(scores) == 8 and scores == sorted(scores, reverse=True) and guess["candidates"][0]["winner"]
    assert guess["score"] == scores[0] and 0 < guess["candidates"][0]["fraction"] <= 1
    coarse = client.get(f"{CORRIDOR}/guess?data=2&level=0&top=3").json()
    assert coarse["cube_size"] == guess["levels"][0] and coarse["cube_size"] > guess["cube_size"]

    applied = client.post(f"{CORRIDOR}/guess/apply", json={"data": 2, "candidate": 1}, headers={"X-Author": "fay"})
    assert applied.status_code == 200, applied.text
    assert applied.json()["revision"] == 1 and applied.json()["fitness"] > 0.5
    truth = true_poses(4)
    poses = poses_of(client, "corridor")
    assert pose_difference(invert(poses[1]) @ poses[2], invert(truth[1]) @ truth[2])[0] < 0.05
    entry = client.get(f"{CORRIDOR}/journal").json()[-1]
    assert entry["kind"] == "icp_from_candidate" and entry["parameters"]["candidate"] == 1
    assert client.get(f"{CORRIDOR}/guess?data=0").status_code == 404  # scan 0 has no previous scan
    assert client.get(f"{CORRIDOR}/guess?data=2&level=7").status_code == 422


def test_a_registration_run_stores_a_trace_that_replays_to_its_poses(client):
    wait(client, client.post(f"{CORRIDOR}/jobs", json={"kind": "register"}, headers={"X-Author": "gus"}))
    listed = client.get(f"{CORRIDOR}/traces").json()
    assert len(listed) == 1 and listed[0]["bytes"] > 1000
    name = listed[0]["name"]
    entry = next(e for e in client.get(f"{CORRIDOR}/journal").json() if e["kind"] == "register")
    assert entry["parameters"]["trace"] == name and entry["author"] == "gus"
    trace = client.get(f"{CORRIDOR}/traces/{name}").json()
    frames = replay_frames(trace)
    kinds = [f.kind for f in frames]
    assert kinds.count("ScanRegistered") == 3 and kinds[-1] == "Finished" and "IcpIterated" in kinds
    shown = [np.asarray(p) for p in trace["initial_poses"]]
    for frame in frames:  # what a replay does: apply each frame's poses, nothing else
        for k, pose in frame.moved.items():
            shown[k] = pose
    for got, committed in zip(shown, poses_of(client, "corridor"), strict=True):
        assert np.allclose(got, committed, atol=1e-9)
    icp_frame = next(f for f in frames if f.kind == "IcpIterated")
    assert icp_frame.current is not None and icp_frame.model and icp_frame.rms_history
    assert client.get(f"{CORRIDOR}/traces/nope").status_code == 404
    for encoded in ("%2E%2E", "..%5Cjournal"):  # decoded before routing: the handler's own guard answers
        refused = client.get(f"{CORRIDOR}/traces/{encoded}")
        assert refused.status_code == 404 and refused.json()["detail"].startswith("no trace '..")


def test_residual_summary_over_the_graph(client):
    summary = client.get(f"{CORRIDOR}/residuals").json()
    assert [(e["i"], e["j"]) for e in summary["edges"]] == [(0, 1), (1, 2), (2, 3)]
    assert 0 < summary["rms"] < 0.4 and 0.5 < summary["paired"] <= 1.0
    assert client.get(f"{CORRIDOR}/residuals?rev=5").status_code == 422
