"""The session folder: config round trip, scan cache, append-only journal, revisions, undo/redo."""

from __future__ import annotations

import sqlite3
import threading

import numpy as np
import pytest

from slam6d.errors import FormatError, InvalidValueError, SessionError
from slam6d.session import JOURNAL_FILE, SESSION_FILE, Session, list_sessions
from tests.session_fixtures import true_poses, write_corridor_scans


@pytest.fixture
def session(tmp_path):
    write_corridor_scans(tmp_path / "s" / "scans", scans=3, points=500)
    return Session.create(tmp_path / "s", 'Corridor "A" — test', "scans", engine={"voxel_size": 0.2})


def test_create_writes_config_that_reopens_identically(session, tmp_path):
    reopened = Session.open(tmp_path / "s")
    assert reopened.config.name == 'Corridor "A" — test'
    assert reopened.config.format_name == "uos"
    assert reopened.config.frame == "uos"
    assert reopened.config.sources == ("scans",)
    assert reopened.config.engine == {"voxel_size": 0.2}
    assert len(reopened.scan_files()) == 3
    assert (tmp_path / "s" / JOURNAL_FILE).exists()


def test_load_sequence_is_canonical_and_creates_revision_zero(session):
    assert session.journal.entries() == []
    sequence = session.load_sequence()
    assert len(sequence) == 3
    assert session.revision == 0
    for scan, expected in zip(sequence.scans, true_poses(3), strict=True):
        # uos poses are written with 6 decimals in cm/deg: sub-millimetre agreement
        assert np.allclose(scan.pose[:3, 3], expected[:3, 3], atol=1e-4)
        assert np.allclose(scan.pose[:3, :3], expected[:3, :3], atol=1e-5)
    # the corridor floor is at z=0 in the world: canonical z up after conversion
    world = np.concatenate([s.world_points() for s in sequence.scans])
    assert world[:, 2].min() == pytest.approx(0.0, abs=0.01)
    assert session.journal.entries()[0].kind == "import"


def test_cache_is_used_and_invalidated_when_a_source_changes(session, tmp_path):
    first = session.load_sequence()
    cache = tmp_path / "s" / "cache" / "scans.npz"
    assert cache.exists()
    again = Session.open(tmp_path / "s").load_sequence()
    assert np.allclose(again[1].points, first[1].points, atol=1e-5)
    # overwrite one scan: the cache must not serve stale points
    write_corridor_scans(tmp_path / "s" / "scans", scans=3, points=400, seed=7)
    changed = Session.open(tmp_path / "s").load_sequence()
    assert len(changed[0]) == 400


def test_commit_undo_redo_and_history_is_append_only(session):
    session.load_sequence()
    base = session.poses()
    moved = [p.copy() for p in base]
    moved[2][0, 3] += 1.5
    rev1 = session.journal.commit(moved, "ana", "manual_move", {"scan": 2}, graph={"loops": [[0, 2]]})
    assert rev1 == 1 and session.revision == 1
    assert session.poses()[2][0, 3] == pytest.approx(base[2][0, 3] + 1.5)
    assert session.graph() == {"loops": [[0, 2]]}
    assert session.journal.can_undo() and not session.journal.can_redo()

    assert session.journal.undo("bob") == 0
    assert session.poses()[2][0, 3] == pytest.approx(base[2][0, 3])
    assert session.journal.can_redo()
    assert session.journal.redo("ana") == 1
    assert session.revision == 1
    # old revisions stay readable
    assert np.allclose(session.poses(rev=0)[2], base[2])

    # a new edit after an undo clears the redo stack but keeps the undone revision in the store
    session.journal.undo("bob")
    rev2 = session.journal.commit(base, "carl", "relax")
    assert rev2 == 2 and not session.journal.can_redo()
    assert session.journal.revisions() == [0, 1, 2]
    kinds = [(e.kind, e.author) for e in session.journal.entries()]
    assert kinds == [
        ("import", "system"),
        ("manual_move", "ana"),
        ("undo", "bob"),
        ("redo", "ana"),
        ("undo", "bob"),
        ("relax", "carl"),
    ]
    assert session.journal.entries()[1].parameters == {"scan": 2}
    assert all(e.time.endswith("+00:00") for e in session.journal.entries())


def test_undo_at_the_start_and_redo_with_nothing_undone_fail_clearly(session):
    session.load_sequence()
    with pytest.raises(SessionError, match="nothing to undo"):
        session.journal.undo("ana")
    with pytest.raises(SessionError, match="nothing to redo"):
        session.journal.redo("ana")


def test_unknown_revision_and_non_finite_poses_are_refused(session):
    session.load_sequence()
    with pytest.raises(SessionError, match="no revision 5"):
        session.poses(rev=5)
    bad = session.poses()
    bad[0][0, 3] = np.nan
    with pytest.raises(InvalidValueError, match=r"poses\[0\]: must hold finite numbers"):
        session.journal.commit(bad, "ana", "edit")
    assert session.journal.revisions() == [0]


def test_poses_without_loading_materialise_revision_zero(session):
    poses = session.poses()
    assert len(poses) == 3 and session.revision == 0


def test_concurrent_commits_from_two_handles_serialise(session, tmp_path):
    session.load_sequence()
    base = session.poses()
    other = Session.open(tmp_path / "s")
    errors: list[BaseException] = []

    def work(handle: Session, author: str) -> None:
        try:
            for _ in range(10):
                handle.journal.commit(base, author, "edit")
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(h, a)) for h, a in ((session, "a"), (other, "b"))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert session.journal.revisions() == list(range(21))
    # every revision's parent is the one current when it was made: a single chain
    with sqlite3.connect(tmp_path / "s" / JOURNAL_FILE) as conn:
        parents = [row[0] for row in conn.execute("SELECT parent FROM revisions ORDER BY number")]
    assert parents == [None, *range(20)]


def test_camera_path_round_trip_and_engine_parameters(session, tmp_path):
    assert session.camera_path() == []
    keys = [
        {"position": [0.0, 0.0, 10.0], "orientation_wxyz": [1.0, 0.0, 0.0, 0.0], "fov_deg": 60.0},
        {"position": [9.0, 1.0, 3.0], "orientation_wxyz": [0.0, 1.0, 0.0, 0.0], "fov_deg": 45.0},
    ]
    session.set_camera_path(keys, "ana")
    session.update_engine({"max_iterations": 40}, "ana")
    reopened = Session.open(tmp_path / "s")
    assert reopened.camera_path() == keys
    assert reopened.config.engine == {"voxel_size": 0.2, "max_iterations": 40}


def test_create_refuses_bad_input_and_writes_nothing(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError):
        Session.create(tmp_path / "a", "a", tmp_path / "empty", "uos")
    with pytest.raises(SessionError, match="does not exist"):
        Session.create(tmp_path / "b", "b", tmp_path / "missing", "uos")
    write_corridor_scans(tmp_path / "scans", scans=1, points=50)
    with pytest.raises(SessionError, match="name"):
        Session.create(tmp_path / "c", "", tmp_path / "scans", "uos")
    with pytest.raises(SessionError, match="unknown frame"):
        Session.create(tmp_path / "d", "d", tmp_path / "scans", "uos", frame="martian")
    assert not any((tmp_path / x).exists() for x in "abcd")
    Session.create(tmp_path / "e", "e", tmp_path / "scans")
    with pytest.raises(SessionError, match="already exists"):
        Session.create(tmp_path / "e", "e", tmp_path / "scans")


def test_malformed_session_toml_names_the_file(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / SESSION_FILE).write_text("name = \n")
    with pytest.raises(FormatError, match=r"session\.toml"):
        Session.open(tmp_path / "x")
    (tmp_path / "x" / SESSION_FILE).write_text('name = "x"\n[source]\nformat = "uos"\n')
    with pytest.raises(FormatError, match="paths"):
        Session.open(tmp_path / "x")
    with pytest.raises(SessionError, match="not a session folder"):
        Session.open(tmp_path / "nothing")


def test_list_sessions_finds_only_session_folders(session, tmp_path):
    (tmp_path / "other").mkdir()
    assert [s.name for s in list_sessions(tmp_path)] == ['Corridor "A" — test']
