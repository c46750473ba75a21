"""A registration job whose stage fails keeps its poses as a revision and says so (the workbench side
of "no lost work")."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient

from app.server import create_app
from slam6d.geometry import UOS, invert, make_pose, pose_difference
from slam6d.io.uos import write_uos_scan
from slam6d.session import Session
from tests.simulated_loop import simulated_loop


def test_a_disconnected_registration_becomes_a_revision_with_its_components(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Four scans of the simulated loop, then the same four 1 km away: the run falls into two
    components; the job fails naming them, and the poses it has become revision 1."""
    sim = simulated_loop(scans=8, points=20000, seed=1, first=4, loop_length=16.0, loop_width=10.0)
    folder = tmp_path / "sessions" / "apart"
    far = make_pose(np.eye(3), [1000.0, 0.0, 0.0])
    for k, scan in enumerate([*sim.sequence.scans, *sim.sequence.scans]):
        pose = scan.pose if k < 4 else far @ scan.pose
        write_uos_scan(folder / "scans", k, UOS.points_to_native(scan.points), UOS.pose_to_native(pose))
    # the global feature guess would (rightly) find the far copies overlapping the first scans
    Session.create(folder, "Apart", "scans", engine={"loops": False, "feature_guess": False})
    with TestClient(create_app(tmp_path / "sessions", viewers=False), base_url="http://127.0.0.1") as client:
        started = client.post("/api/sessions/apart/jobs", json={"kind": "register"}, headers={"X-Author": "ana"})
        job = client.app.state.workbench.jobs.wait(started.json()["id"], timeout=300)
        assert job.status == "failed"
        assert (
            "relaxation stage failed" in job.message and "kept as revision 1 in 2 connected components" in job.message
        )
        assert job.result["revision"] == 1 and job.result["components"] == [[0, 1, 2, 3], [4, 5, 6, 7]]
        assert job.result["failure"]["stage"] == "relaxation"
        entry = next(e for e in client.get("/api/sessions/apart/journal").json() if e["kind"] == "register")
        assert entry["author"] == "ana" and entry["parameters"]["components"] == [[0, 1, 2, 3], [4, 5, 6, 7]]
        # the view's guardrail over REST: the pieces lum would relax now, and the failure they came from
        pieces = client.get("/api/sessions/apart/components", params={"method": "lum"}).json()
        assert pieces["components"] == [[0, 1, 2, 3], [4, 5, 6, 7]] and pieces["ranges"] == "[0-3]; [4-7]"
        assert pieces["failure"]["stage"] == "relaxation" and pieces["failure"]["revision"] == 1
        assert pieces["message"].startswith("the relaxation stage failed (revision 1): ")
        rows = np.array(
            [
                [float(v) for v in line.split()]
                for line in client.get("/api/sessions/apart/poses").text.split("\n")
                if line
            ]
        )
        poses = [np.vstack([r.reshape(3, 4), [0, 0, 0, 1]]) for r in rows]
    for offset in (0, 4):  # each component registered and relaxed on its own
        for k in range(1, 4):
            relative = invert(poses[offset]) @ poses[offset + k]
            metres, _ = pose_difference(relative, invert(sim.truth[0]) @ sim.truth[k])
            assert metres < 0.03, (offset + k, metres)
