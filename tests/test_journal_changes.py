"""No lost update in the journal: edits are changes applied to the head inside the write transaction."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from slam6d.errors import InvalidValueError, SessionError
from slam6d.journal import Change, EditConflictError, Journal, StaleRevisionError, expecting


def translation(x: float, y: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, 0.0)
    return pose


@pytest.fixture
def journal(tmp_path: Path) -> Journal:
    found = Journal(tmp_path / "journal.sqlite")
    found.commit([translation(float(k)) for k in range(4)], "system", "import")
    return found


def head_poses(journal: Journal) -> list[np.ndarray]:
    head = journal.head
    assert head is not None
    found = journal.revision(head)
    assert found is not None
    return found.poses


def test_a_change_keeps_what_others_did_to_other_scans(journal: Journal) -> None:
    journal.apply(Change({1: translation(10.0)}), "ann", "manual_move")
    journal.apply(Change({2: translation(20.0)}), "bob", "manual_move")
    poses = head_poses(journal)
    assert poses[1][0, 3] == 10.0 and poses[2][0, 3] == 20.0 and poses[3][0, 3] == 3.0


def test_graph_changes_are_functions_of_the_head(journal: Journal) -> None:
    def add(edge: list[int]):  # type: ignore[no-untyped-def]
        return lambda graph: {**graph, "loops": [*graph.get("loops", []), edge]}

    journal.apply(Change(graph=add([0, 2])), "ann", "add_edge")
    journal.apply(Change(graph=add([1, 3])), "bob", "add_edge")
    head = journal.revision(journal.head or 0)
    assert head is not None and head.graph["loops"] == [[0, 2], [1, 3]]


def test_threads_moving_different_scans_all_keep_their_moves(journal: Journal) -> None:
    barrier = threading.Barrier(4)

    def move(k: int) -> None:
        barrier.wait()
        for step in range(5):
            journal.apply(Change({k: translation(100.0 * k + step)}), f"user{k}", "manual_move")

    threads = [threading.Thread(target=move, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    poses = head_poses(journal)
    assert [p[0, 3] for p in poses] == [4.0, 104.0, 204.0, 304.0]
    assert len(journal.revisions()) == 1 + 20


def test_stale_expectation_is_refused_with_what_happened_since(journal: Journal) -> None:
    seen = journal.head
    journal.apply(Change({1: translation(5.0)}), "ann", "manual_move")
    with expecting(seen), pytest.raises(StaleRevisionError) as refused:
        journal.apply(Change({2: translation(7.0)}), "bob", "manual_move")
    assert refused.value.head == 1 and refused.value.expected == 0
    assert [(e.head, e.author, e.kind) for e in refused.value.since] == [(1, "ann", "manual_move")]
    assert "manual_move by ann" in str(refused.value)
    assert head_poses(journal)[2][0, 3] == 2.0  # nothing applied
    with expecting(journal.head):
        journal.apply(Change({2: translation(7.0)}), "bob", "manual_move")
    assert head_poses(journal)[2][0, 3] == 7.0


def test_stale_expectation_also_guards_documents_and_notes(journal: Journal) -> None:
    journal.apply(Change({1: translation(5.0)}), "ann", "manual_move")
    with expecting(0):
        with pytest.raises(StaleRevisionError):
            journal.update_document("bob", "camera_path", lambda doc: {"keyframes": [1]})
        with pytest.raises(StaleRevisionError):
            journal.append("bob", "parameters", {"voxel_size": 1})
    assert journal.latest("camera_path") is None


def test_job_from_an_older_revision_rebases_onto_untouched_scans(journal: Journal) -> None:
    base = journal.head
    journal.apply(Change({0: translation(-50.0)}), "ann", "manual_move")  # while the job ran
    relaxed = [translation(0.0), translation(1.5), translation(2.5), translation(3.5)]  # scan 0 held fixed
    journal.commit(relaxed, "job", "relax_lum", base=base)
    poses = head_poses(journal)
    assert poses[0][0, 3] == -50.0  # ann's move is kept
    assert [p[0, 3] for p in poses[1:]] == [1.5, 2.5, 3.5]


def test_job_touching_a_scan_moved_meanwhile_is_refused_naming_the_edit(journal: Journal) -> None:
    base = journal.head
    journal.apply(Change({2: translation(-50.0)}), "ann", "manual_move")
    head = journal.head
    with pytest.raises(EditConflictError) as refused:
        journal.commit([translation(k + 0.5) for k in range(4)], "job", "relax_lum", base=base)
    assert refused.value.scans == [2]
    assert refused.value.entry is not None and refused.value.entry.author == "ann"
    assert "scan 2 was changed by ann (manual_move, revision 1" in str(refused.value)
    assert journal.head == head and head_poses(journal)[2][0, 3] == -50.0


def test_undo_and_redo_named_by_revision_are_idempotent(journal: Journal) -> None:
    journal.apply(Change({1: translation(5.0)}), "ann", "manual_move")
    assert journal.undo("ann", revision=1) == 0
    assert journal.undo("ann", revision=1) == 0  # the retry answers, it does not undo again
    assert [e.kind for e in journal.entries()].count("undo") == 1
    assert journal.redo("ann", revision=0) == 1
    assert journal.redo("ann", revision=0) == 1
    assert [e.kind for e in journal.entries()].count("redo") == 1
    journal.apply(Change({2: translation(9.0)}), "bob", "manual_move")
    with pytest.raises(StaleRevisionError):
        journal.undo("ann", revision=1)  # ann saw revision 1; bob's edit came after it


def test_documents_are_changed_in_place_of_being_overwritten(journal: Journal) -> None:
    barrier = threading.Barrier(6)

    def add(n: int) -> None:
        barrier.wait()
        journal.update_document(
            f"user{n}", "camera_path", lambda doc: {"keyframes": [*(doc or {"keyframes": []})["keyframes"], n]}
        )

    threads = [threading.Thread(target=add, args=(n,)) for n in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    latest = journal.latest("camera_path")
    assert latest is not None and sorted(latest.parameters["keyframes"]) == list(range(6))


def test_bad_changes_are_refused_and_nothing_is_stored(journal: Journal) -> None:
    with pytest.raises(SessionError, match="no scan 9"):
        journal.apply(Change({9: translation(1.0)}), "ann", "manual_move")
    with pytest.raises(InvalidValueError, match=r"poses\[1\]: must hold finite numbers"):
        journal.apply(Change({1: translation(float("nan"))}), "ann", "manual_move")
    assert journal.revisions() == [0]
