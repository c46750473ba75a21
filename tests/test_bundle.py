"""Session bundles: a round trip keeps every revision; every malicious zip is refused with nothing written."""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from slam6d.archive import ArchiveError, ArchiveLimits, extract_zip
from slam6d.bundle import MANIFEST, export_bundle, import_bundle, local_source_finder
from slam6d.cli import app
from slam6d.geometry import make_pose, rot_z
from slam6d.session import JOURNAL_FILE, Session
from tests.session_fixtures import corridor_session

KEYFRAME = {"position": [1.0, 2.0, 3.0], "orientation_wxyz": [1.0, 0.0, 0.0, 0.0], "fov_deg": 55.0}


@pytest.fixture
def edited(tmp_path: Path) -> Session:
    """A session with history: import, two edits, an undo, a redo, a camera path and a trace file."""
    session = Session.open(corridor_session(tmp_path / "origin", scans=3, points=400))
    session.load_sequence()
    poses = session.poses()
    poses[1] = poses[1] @ make_pose(rot_z(0.1), [0.2, 0.0, 0.0])
    session.journal.commit(poses, "ana", "move", {"scan": 1})
    poses[2] = poses[2] @ make_pose(rot_z(-0.05), [0.0, 0.3, 0.0])
    session.journal.commit(poses, "ben", "move", {"scan": 2})
    session.journal.undo("ana")
    session.journal.redo("ana")
    session.journal.undo("ben")
    session.set_camera_path([KEYFRAME], "ana")
    (session.folder / "traces").mkdir()
    (session.folder / "traces" / "run-1.json").write_text('{"events": []}')
    return session


def _history(session: Session) -> tuple[list[tuple], dict[int, tuple]]:
    entries = [(e.time, e.author, e.kind, e.parameters, e.head, e.revision) for e in session.journal.entries()]
    revisions = {}
    for number in session.journal.revisions():
        rev = session.journal.revision(number)
        assert rev is not None
        revisions[number] = (rev.parent, np.stack(rev.poses).tobytes(), json.dumps(rev.graph))
    return entries, revisions


@pytest.mark.parametrize("with_scans", [True, False])
def test_round_trip_keeps_every_revision_and_entry(edited: Session, tmp_path: Path, with_scans: bool) -> None:
    summary = export_bundle(edited, tmp_path / "b.zip", include_scans=with_scans)
    names = zipfile.ZipFile(summary.path).namelist()
    assert {MANIFEST, "session.toml", JOURNAL_FILE, "camera_path.json", "traces/run-1.json"} <= set(names)
    assert any(n.startswith("sources/0/scan000") for n in names) == with_scans
    assert not any(n.startswith("cache/") for n in names)

    finder = local_source_finder(None) if not with_scans else None
    copy = import_bundle(summary.path, tmp_path / "team", find_source=finder, author="cy")
    assert copy.folder.parent == tmp_path / "team" and copy.name == edited.name
    entries, revisions = _history(copy)
    original_entries, original_revisions = _history(edited)
    assert revisions == original_revisions
    assert entries[:-1] == original_entries and entries[-1][1:3] == ("cy", "bundle_import")
    assert copy.journal.head == edited.journal.head and copy.journal.redo_stack() == edited.journal.redo_stack()
    assert copy.camera_path() == edited.camera_path()
    assert (copy.folder / "traces" / "run-1.json").read_text() == '{"events": []}'
    sequence = copy.load_sequence()  # the scans are reachable: inside the bundle, or where they were
    np.testing.assert_allclose(sequence.poses()[1], edited.poses()[1], atol=1e-12)


def test_a_bundle_without_scans_is_refused_where_outside_folders_are_not_allowed(
    edited: Session, tmp_path: Path
) -> None:
    bundle = export_bundle(edited, tmp_path / "b.zip").path
    with pytest.raises(ArchiveError, match="may not look for them; export it with its scans"):
        import_bundle(bundle, tmp_path / "team")
    assert list((tmp_path / "team").iterdir()) == []


def _scan_folder(session: Session) -> Path:
    (source,) = session.source_paths()
    return source.resolve()


def test_a_bundle_without_scans_is_relinked_under_another_data_root(edited: Session, tmp_path: Path) -> None:
    """The same scans under another machine's data root: found by their place in it, hashes checked."""
    origin_root = _scan_folder(edited).parent
    bundle = export_bundle(edited, tmp_path / "b.zip", data_root=origin_root).path
    manifest = json.loads(zipfile.ZipFile(bundle).read(MANIFEST))
    (record,) = manifest["sources"]
    assert record["data_root_path"] == _scan_folder(edited).name
    assert {f["path"] for f in record["files"]} >= {"scan000.3d", "scan001.3d", "scan002.3d"}

    other_root = tmp_path / "elsewhere" / "data"
    shutil.copytree(_scan_folder(edited), other_root / _scan_folder(edited).name)
    shutil.rmtree(_scan_folder(edited))  # the recorded absolute path is gone: only the data root has them
    copy = import_bundle(bundle, tmp_path / "team", find_source=local_source_finder(other_root))
    assert copy.source_paths() == [other_root / record["data_root_path"]]
    np.testing.assert_allclose(copy.load_sequence().poses()[1], edited.poses()[1], atol=1e-12)
    assert len(copy.load_sequence().scans[2].points) == 400


@pytest.mark.parametrize("damage", ["missing", "altered"])
def test_a_bundle_without_scans_is_refused_naming_what_is_missing(edited: Session, tmp_path: Path, damage: str) -> None:
    origin_root = _scan_folder(edited).parent
    bundle = export_bundle(edited, tmp_path / "b.zip", data_root=origin_root).path
    scan = _scan_folder(edited) / "scan001.3d"
    if damage == "missing":
        scan.unlink()
    else:
        scan.write_text(scan.read_text().replace("0", "1", 1))
    expected = "missing scan001.3d" if damage == "missing" else "'scan001.3d' differs from the exported file"
    with pytest.raises(ArchiveError, match=f"scan source 0 .*{expected}"):
        import_bundle(bundle, tmp_path / "team", find_source=local_source_finder(origin_root))
    assert list((tmp_path / "team").iterdir()) == []


def test_a_bundle_with_scans_cannot_point_at_a_folder_outside_it(edited: Session, tmp_path: Path) -> None:
    """Only sources found and hashed by the import are opened: a with-scans bundle naming /etc is refused."""
    bundle = export_bundle(edited, tmp_path / "b.zip", include_scans=True).path
    names = zipfile.ZipFile(bundle).namelist()
    toml = zipfile.ZipFile(bundle).read("session.toml").decode()
    evil_toml = toml.replace('"sources/0"', f'"{_scan_folder(edited)}"').encode()
    assert evil_toml != toml.encode() and "session.toml" in names
    evil = tmp_path / "evil.zip"
    with zipfile.ZipFile(bundle) as source, zipfile.ZipFile(evil, "w") as target:
        manifest = json.loads(source.read(MANIFEST))
        for item in manifest["files"]:
            if item["path"] == "session.toml":
                item["sha256"], item["bytes"] = hashlib.sha256(evil_toml).hexdigest(), len(evil_toml)
        for name in names:
            data = evil_toml if name == "session.toml" else source.read(name)
            target.writestr(name, json.dumps(manifest) if name == MANIFEST else data)
    with pytest.raises(ArchiveError, match="is not in the bundle"):
        import_bundle(evil, tmp_path / "team", find_source=local_source_finder(None))
    assert list((tmp_path / "team").iterdir()) == []


def test_cli_imports_a_bundle_without_scans_from_its_data_root(edited: Session, tmp_path: Path) -> None:
    runner = CliRunner()
    root = str(_scan_folder(edited).parent)
    done = runner.invoke(app, ["bundle", "export", str(edited.folder), str(tmp_path / "c.zip"), "--data-root", root])
    assert done.exit_code == 0, done.output
    assert "without scans" in done.output
    done = runner.invoke(
        app, ["bundle", "import", str(tmp_path / "c.zip"), str(tmp_path / "team"), "--data-root", root]
    )
    assert done.exit_code == 0, done.output
    (_scan_folder(edited) / "scan000.3d").unlink()
    done = runner.invoke(app, ["bundle", "import", str(tmp_path / "c.zip"), str(tmp_path / "again")])
    assert done.exit_code != 0 and "missing scan000.3d" in str(done.exception)  # main() prints it as one line


def test_cli_export_and_import(edited: Session, tmp_path: Path) -> None:
    runner = CliRunner()
    done = runner.invoke(app, ["bundle", "export", str(edited.folder), str(tmp_path / "c.zip"), "--scans"])
    assert done.exit_code == 0, done.output
    assert "with scans" in done.output
    done = runner.invoke(app, ["bundle", "import", str(tmp_path / "c.zip"), str(tmp_path / "team")])
    assert done.exit_code == 0, done.output
    assert f"at revision {edited.journal.head}" in done.output


# ------------------------------------------------------------------ malicious zips


def _rezip(bundle: Path, change: dict[str, bytes | None], extra: list[tuple[zipfile.ZipInfo | str, bytes]]) -> bytes:
    """The bundle with entries replaced (None removes one) and extra entries appended, manifest unchanged."""
    out = io.BytesIO()
    with zipfile.ZipFile(bundle) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as target:
        for info in source.infolist():
            data = change.get(info.filename, source.read(info.filename))
            if data is not None:
                target.writestr(info.filename, data)
        for name, data in extra:
            target.writestr(name, data)
    return out.getvalue()


def _symlink(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.external_attr = (0o120777 << 16) | 0x20
    return info


def _bad_crc(bundle: Path) -> bytes:
    """The bundle stored uncompressed with one byte of session.toml flipped (its CRC no longer matches)."""
    out = io.BytesIO()
    with zipfile.ZipFile(bundle) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as target:
        for info in source.infolist():
            target.writestr(info.filename, source.read(info.filename))
    data = bytearray(out.getvalue())
    at = data.index(b"name = ")
    data[at] ^= 0x01
    return bytes(data)


MALICIOUS = {
    "zip-slip": (lambda b: _rezip(b, {}, [("../escaped.txt", b"x")]), "unsafe path"),
    "deep zip-slip": (lambda b: _rezip(b, {}, [("traces/../../escaped.txt", b"x")]), "unsafe path"),
    "absolute path": (lambda b: _rezip(b, {}, [("/tmp/escaped.txt", b"x")]), "unsafe path"),
    "windows path": (lambda b: _rezip(b, {}, [("..\\escaped.txt", b"x")]), "unsafe path"),
    "symlink entry": (lambda b: _rezip(b, {}, [(_symlink("traces/link"), b"/etc/passwd")]), "symbolic link"),
    "nested archive by name": (lambda b: _rezip(b, {}, [("traces/inner.zip", b"not really")]), "nested archives"),
    "nested archive by content": (
        lambda b: _rezip(b, {}, [("traces/inner.json", b"PK\x03\x04" + bytes(100))]),
        "nested archives",
    ),
    "zip bomb by ratio": (lambda b: _rezip(b, {}, [("traces/zeros.json", bytes(40 << 20))]), "zip bomb"),
    "hash mismatch": (lambda b: _rezip(b, {"traces/run-1.json": b'{"events": [1]}'}, []), "does not match its sha256"),
    "unlisted file": (lambda b: _rezip(b, {}, [("traces/extra.json", b"{}")]), "not in manifest.json"),
    "missing file": (lambda b: _rezip(b, {"traces/run-1.json": None}, []), "missing from the zip"),
    "no manifest": (lambda b: _rezip(b, {MANIFEST: None}, []), "no manifest.json"),
    "bad crc": (_bad_crc, "damaged"),
    "not a zip": (lambda b: b"this is not a zip file at all", "not a valid zip"),
}


@pytest.mark.parametrize("kind", sorted(MALICIOUS))
def test_each_malicious_bundle_is_refused_with_nothing_written(edited: Session, tmp_path: Path, kind: str) -> None:
    make, reason = MALICIOUS[kind]
    bundle = export_bundle(edited, tmp_path / "b.zip", include_scans=True).path
    evil = tmp_path / f"{kind}.zip"
    evil.write_bytes(make(bundle))
    sessions = tmp_path / "team" / "sessions"
    sessions.mkdir(parents=True)
    with pytest.raises(ArchiveError, match=reason):
        import_bundle(evil, sessions)
    assert list(sessions.iterdir()) == []
    assert sorted(p.name for p in (tmp_path / "team").iterdir()) == ["sessions"]  # nothing escaped either


def test_zip_bomb_by_total_and_entry_count_are_refused_while_streaming(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for k in range(4):
            zf.writestr(f"part{k}.bin", rng.bytes(1 << 20))  # incompressible: the ratio check stays quiet
    small = ArchiveLimits(max_total_bytes=3 << 20)
    with pytest.raises(ArchiveError, match="expands to more than the limit of 3 MiB") as info:
        extract_zip(io.BytesIO(archive.getvalue()), tmp_path / "out", small)
    assert info.value.too_large
    with pytest.raises(ArchiveError, match="4 entries, more than the limit of 3"):
        extract_zip(io.BytesIO(archive.getvalue()), tmp_path / "out", ArchiveLimits(max_entries=3))
    assert list(tmp_path.iterdir()) == []
    written = extract_zip(io.BytesIO(archive.getvalue()), tmp_path / "out")
    assert [p.as_posix() for p in written] == [f"part{k}.bin" for k in range(4)]
    assert (tmp_path / "out" / "part3.bin").stat().st_size == 1 << 20


def test_a_header_that_lies_about_sizes_is_caught_by_what_actually_expands(tmp_path: Path) -> None:
    """The central directory says 10 bytes; the data inflates to 40 MiB of zeros: the stream is counted."""
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("zeros.bin", bytes(40 << 20))
    data = bytearray(archive.getvalue())
    central = data.rindex(b"PK\x01\x02")
    data[central + 24 : central + 28] = (10).to_bytes(4, "little")  # uncompressed size in the directory
    with pytest.raises(ArchiveError):
        extract_zip(io.BytesIO(bytes(data)), tmp_path / "out")
    assert list(tmp_path.iterdir()) == []
