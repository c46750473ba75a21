"""Every scan format: round trip, broken files (named file and line), NaN points and empty files."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from slam6d.errors import EmptyScanError, FormatError
from slam6d.geometry import UOS, pose_from_xyzrpy
from slam6d.io import read_scan
from slam6d.io.csv import write_csv_cloud
from slam6d.io.e57 import write_e57
from slam6d.io.kitti import write_kitti_bin
from slam6d.io.las import write_las
from slam6d.io.pcd import write_pcd
from slam6d.io.ply import write_ply
from slam6d.io.registry import NonFinitePointsWarning
from slam6d.io.uos import write_uos_scan
from slam6d.io.vtk import write_vtk
from slam6d.io.xyz import write_xyz

RNG = np.random.default_rng(7)
POINTS = RNG.uniform(-20.0, 20.0, size=(200, 3))
INTENSITY = RNG.uniform(0.0, 1.0, size=200).astype(np.float32)

Writer = Callable[[Path, np.ndarray, np.ndarray | None], Path]


def _simple(suffix: str, write: Callable[..., None], **kwargs: object) -> Writer:
    def writer(directory: Path, points: np.ndarray, intensity: np.ndarray | None) -> Path:
        path = directory / f"cloud{suffix}"
        if intensity is None:
            write(path, points, **kwargs)
        else:
            write(path, points, intensity=intensity, **kwargs)
        return path

    return writer


def _write_uos(directory: Path, points: np.ndarray, intensity: np.ndarray | None) -> Path:
    with np.errstate(invalid="ignore"):  # inf * 0 in the axis swap of the NaN test's points
        native = UOS.points_to_native(points)
    return write_uos_scan(directory, 0, native, None)


# name -> (writer, coordinate tolerance in metres, carries intensity)
WRITERS: dict[str, tuple[Writer, float, bool]] = {
    "kitti": (_simple(".bin", lambda p, pts, intensity=None: write_kitti_bin(p, pts, intensity)), 1e-5, True),
    "ply-binary": (_simple(".ply", write_ply, binary=True), 1e-12, True),
    "ply-ascii": (_simple(".ply", write_ply, binary=False), 1e-12, True),
    "pcd-binary": (_simple(".pcd", write_pcd, binary=True), 1e-5, True),
    "pcd-ascii": (_simple(".pcd", write_pcd, binary=False), 1e-5, True),
    "xyz": (_simple(".xyz", write_xyz), 1e-7, True),
    "las": (_simple(".las", write_las), 1e-4, False),  # intensity is quantised to 16 bit
    "laz": (_simple(".laz", write_las), 1e-4, False),
    "e57": (_simple(".e57", write_e57), 1e-5, True),
    "vtk-ascii": (_simple(".vtk", write_vtk, binary=False), 1e-12, False),
    "vtk-binary": (_simple(".vtk", write_vtk, binary=True), 1e-12, False),
    "csv": (_simple(".csv", write_csv_cloud), 1e-7, True),
    "uos": (_write_uos, 1e-4, False),  # 3DTK text keeps 0.01 mm of a centimetre value
}


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_round_trip(tmp_path: Path, kind: str) -> None:
    writer, tolerance, has_intensity = WRITERS[kind]
    path = writer(tmp_path, POINTS, INTENSITY if has_intensity else None)
    scan = read_scan(path)
    assert len(scan) == len(POINTS)
    np.testing.assert_allclose(scan.points, POINTS, atol=tolerance)
    if has_intensity:
        assert scan.intensity is not None
        np.testing.assert_allclose(scan.intensity, INTENSITY, atol=1e-6)


def test_las_intensity_kept_as_16_bit(tmp_path: Path) -> None:
    path = tmp_path / "i.laz"
    write_las(path, POINTS, intensity=INTENSITY)
    scan = read_scan(path)
    np.testing.assert_allclose(scan.intensity / 65535.0, INTENSITY, atol=1e-4)


# ---------------------------------------------------------------- NaN and empty


NAN_KINDS = sorted(k for k in WRITERS if k not in ("las", "laz", "e57"))  # see dedicated tests below


@pytest.mark.parametrize("kind", NAN_KINDS)
def test_nan_points_are_dropped_with_a_warning(tmp_path: Path, kind: str) -> None:
    writer, _, _ = WRITERS[kind]
    points = POINTS.copy()
    points[5] = np.nan
    points[9, 2] = np.inf
    path = writer(tmp_path, points, None)
    with pytest.warns(NonFinitePointsWarning, match=path.name):
        scan = read_scan(path)
    assert len(scan) == len(POINTS) - 2
    assert np.isfinite(scan.points).all()


def test_e57_invalid_points_are_dropped(tmp_path: Path) -> None:
    """E57 marks missing returns with an invalid-state flag rather than NaN."""
    import pye57

    path = tmp_path / "invalid.e57"
    state = np.zeros(len(POINTS), dtype=np.int8)
    state[[3, 4]] = 1
    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw(
        {
            "cartesianX": POINTS[:, 0],
            "cartesianY": POINTS[:, 1],
            "cartesianZ": POINTS[:, 2],
            "cartesianInvalidState": state,
        }
    )
    e57.close()
    assert len(read_scan(path)) == len(POINTS) - 2


def test_las_cannot_hold_nan_and_the_map_writer_drops_it(tmp_path: Path) -> None:
    from slam6d.io.map import write_map

    points = POINTS.copy()
    points[0] = np.nan
    path = write_map(tmp_path / "map.laz", points, intensity=INTENSITY)
    assert len(read_scan(path)) == len(POINTS) - 1


def _empty_e57(path: Path) -> None:
    import pye57

    pye57.E57(str(path), mode="w").close()


EMPTY_FILES: dict[str, Callable[[Path], Path]] = {
    "kitti": lambda d: _touch(d / "e.bin", b""),
    "ply": lambda d: _call(write_ply, d / "e.ply", np.empty((0, 3))),
    "ply-ascii": lambda d: _call(write_ply, d / "e.ply", np.empty((0, 3)), binary=False),
    "pcd": lambda d: _call(write_pcd, d / "e.pcd", np.empty((0, 3))),
    "pcd-ascii": lambda d: _call(write_pcd, d / "e.pcd", np.empty((0, 3)), binary=False),
    "xyz": lambda d: _touch(d / "e.xyz", b""),
    "xyz-comments": lambda d: _touch(d / "e.xyz", b"# nothing here\n\n"),
    "pts-count-only": lambda d: _touch(d / "e.pts", b"0\n"),
    "las": lambda d: _call(write_las, d / "e.las", np.empty((0, 3))),
    "e57": lambda d: _call(_empty_e57, d / "e.e57"),
    "vtk": lambda d: _call(write_vtk, d / "e.vtk", np.empty((0, 3))),
    "csv": lambda d: _touch(d / "e.csv", b"x,y,z\n"),
    "uos": lambda d: _touch(d / "scan000.3d", b""),
}


def _touch(path: Path, content: bytes) -> Path:
    path.write_bytes(content)
    return path


def _call(write: Callable[..., None], path: Path, *args: object, **kwargs: object) -> Path:
    write(path, *args, **kwargs)
    return path


@pytest.mark.parametrize("kind", sorted(EMPTY_FILES))
def test_empty_file_is_an_empty_scan_error(tmp_path: Path, kind: str) -> None:
    path = EMPTY_FILES[kind](tmp_path)
    with pytest.raises(EmptyScanError, match=path.name):
        read_scan(path)


# ---------------------------------------------------------------- broken files


def _assert_format_error(path: Path, line: int | None = None, match: str | None = None) -> FormatError:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonFinitePointsWarning)
        with pytest.raises(FormatError) as info:
            read_scan(path)
    message = str(info.value)
    assert path.name in message
    if line is not None:
        assert f"{path.name}:{line}:" in message, message
        assert info.value.line == line
    if match is not None:
        assert match in message, message
    return info.value


def _text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_kitti_size_not_multiple_of_16(tmp_path: Path) -> None:
    path = write_kitti_bin_path(tmp_path)
    path.write_bytes(path.read_bytes()[:-5])
    _assert_format_error(path, match="multiple of 16")


def write_kitti_bin_path(directory: Path) -> Path:
    path = directory / "000000.bin"
    write_kitti_bin(path, POINTS, INTENSITY)
    return path


def test_ply_ascii_non_number_names_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.ply"
    write_ply(path, POINTS[:5], binary=False)
    lines = path.read_text().splitlines()
    header_lines = lines.index("end_header") + 1
    lines[header_lines + 2] = "0.5 oops 1.0"
    path.write_text("\n".join(lines) + "\n")
    _assert_format_error(path, line=header_lines + 3, match="field 2 is not a number")


def test_ply_ascii_truncated_names_line(tmp_path: Path) -> None:
    path = tmp_path / "short.ply"
    write_ply(path, POINTS[:5], binary=False)
    lines = path.read_text().splitlines()[:-2]
    path.write_text("\n".join(lines) + "\n")
    _assert_format_error(path, line=len(lines) + 1, match="promises 5 vertices, found 3")


def test_ply_binary_truncated(tmp_path: Path) -> None:
    path = tmp_path / "cut.ply"
    write_ply(path, POINTS)
    path.write_bytes(path.read_bytes()[:-10])
    _assert_format_error(path, match="truncated")


@pytest.mark.parametrize(
    ("header", "line", "match"),
    [
        ("ply\nformat binary_middle_endian 1.0\nelement vertex 1\nend_header\n", 2, "unknown PLY format"),
        ("ply\nformat ascii 1.0\nelement vertex many\nend_header\n", 3, "bad element line"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n", 4, "bad property"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n", None, "lacks properties"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", None, "end_header"),
        ("solid cube\n", None, "not a PLY file"),
    ],
)
def test_ply_bad_header(tmp_path: Path, header: str, line: int | None, match: str) -> None:
    _assert_format_error(_text(tmp_path / "h.ply", header), line=line, match=match)


def test_ply_skips_elements_before_vertices(tmp_path: Path) -> None:
    path = _text(
        tmp_path / "pre.ply",
        "ply\nformat ascii 1.0\nelement camera 2\nproperty float f\nelement vertex 2\nproperty float x\n"
        "property float y\nproperty float z\nproperty uchar intensity\nend_header\n7\n8\n1 2 3 9\n4 5 6 10\n",
    )
    scan = read_scan(path)
    np.testing.assert_allclose(scan.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(scan.intensity, [9, 10])


def test_pcd_ascii_non_number_names_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.pcd"
    write_pcd(path, POINTS[:5], binary=False)
    lines = path.read_text().splitlines()
    lines[-2] = "1 2 x3"
    path.write_text("\n".join(lines) + "\n")
    _assert_format_error(path, line=len(lines) - 1, match="field 3 is not a number")


def test_pcd_ascii_missing_rows(tmp_path: Path) -> None:
    path = tmp_path / "short.pcd"
    write_pcd(path, POINTS[:5], binary=False)
    path.write_text("\n".join(path.read_text().splitlines()[:-1]) + "\n")
    _assert_format_error(path, match="promises 5 points, body has 4")


def test_pcd_binary_truncated(tmp_path: Path) -> None:
    path = tmp_path / "cut.pcd"
    write_pcd(path, POINTS)
    path.write_bytes(path.read_bytes()[:-3])
    _assert_format_error(path, match="truncated")


@pytest.mark.parametrize(
    ("header", "line", "match"),
    [
        ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA zip\n", 7, "unknown DATA"),
        ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH one\n", 5, "WIDTH"),
        ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n", None, "same number"),
        ("VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nDATA ascii\n1 2\n", None, "no field(s) ['z']"),
        ("VERSION 0.7\nCOLOUR red\n", 2, "unexpected PCD header keyword"),
        ("VERSION 0.7\nFIELDS x y z\n", 3, "ends before its DATA"),
        # found by the fuzzer: numpy could not even build the record type for these
        (f"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 {2**64 - 1}\nWIDTH 1\nDATA ascii\n1 2 3\n", None, "COUNT"),
        ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 0 1\nWIDTH 1\nDATA binary\n" + "\0" * 12, None, "at least 1"),
    ],
)
def test_pcd_bad_header(tmp_path: Path, header: str, line: int | None, match: str) -> None:
    _assert_format_error(_text(tmp_path / "h.pcd", header), line=line, match=match)


def _open3d_compressed_pcd(path: Path, points: np.ndarray, intensity: np.ndarray) -> None:
    import open3d as o3d

    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(np.float32)))
    cloud.point.intensity = o3d.core.Tensor(intensity.reshape(-1, 1).astype(np.float32))
    assert o3d.t.io.write_point_cloud(str(path), cloud, compressed=True)


def test_pcd_binary_compressed_written_by_open3d(tmp_path: Path) -> None:
    # A regular grid compresses well, so the LZF back-references are exercised, not only literals.
    grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), np.arange(5.0), indexing="ij"), -1).reshape(-1, 3)
    intensity = np.tile(np.array([0.25, 0.5], dtype=np.float32), len(grid) // 2)
    path = tmp_path / "c.pcd"
    _open3d_compressed_pcd(path, grid, intensity)
    assert path.stat().st_size < grid.size * 4  # really compressed
    scan = read_scan(path)
    np.testing.assert_allclose(scan.points, grid)
    np.testing.assert_allclose(scan.intensity, intensity)


def test_pcd_binary_compressed_corrupt(tmp_path: Path) -> None:
    path = tmp_path / "c.pcd"
    _open3d_compressed_pcd(path, POINTS, INTENSITY)
    raw = bytearray(path.read_bytes())
    body = raw.index(b"DATA binary_compressed\n") + len("DATA binary_compressed\n")
    path.write_bytes(bytes(raw[: body + 8 + 40]))
    _assert_format_error(path, match="truncated")
    raw[body + 8 :] = b"\xff" * (len(raw) - body - 8)  # back-reference before the start
    path.write_bytes(bytes(raw))
    _assert_format_error(path, match="corrupt binary_compressed")


def test_pcd_viewpoint_is_the_pose(tmp_path: Path) -> None:
    pose = pose_from_xyzrpy(1.0, -2.0, 0.5, 0.1, -0.2, 0.3)
    path = tmp_path / "vp.pcd"
    write_pcd(path, POINTS, viewpoint=pose)
    scan = read_scan(path)
    assert scan.has_pose
    np.testing.assert_allclose(scan.pose, pose, atol=1e-6)


def test_xyz_non_number_names_line(tmp_path: Path) -> None:
    path = _text(tmp_path / "bad.xyz", "# header comment\n1 2 3\n4 5 6\n7 8 nine\n")
    _assert_format_error(path, line=4, match="field 3 is not a number")


def test_xyz_ragged_rows_name_line(tmp_path: Path) -> None:
    path = _text(tmp_path / "ragged.txt", "1 2 3 4\n5 6 7 8\n9 10 11\n")
    _assert_format_error(path, line=3, match="expected 4 numbers")


def test_xyz_variants(tmp_path: Path) -> None:
    pts = _text(tmp_path / "a.pts", "2\n1 2 3 40 255 0 0\n4 5 6 50 0 255 0\n")
    scan = read_scan(pts)
    np.testing.assert_allclose(scan.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(scan.intensity, [40, 50])
    comma = _text(tmp_path / "b.txt", "1,2,3\n4,5,6\n")
    np.testing.assert_allclose(read_scan(comma).points, [[1, 2, 3], [4, 5, 6]])
    bad_pts = _text(tmp_path / "c.pts", "2\n1 2 3\n4 5 x\n")
    _assert_format_error(bad_pts, line=3)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_broken(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"cut{suffix}"
    write_las(path, POINTS, intensity=INTENSITY)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(FormatError, match=r"truncated or damaged|cannot read as LAS/LAZ"):
        read_scan(path)
    _assert_format_error(_text(tmp_path / f"junk{suffix}", "not a las file at all"), match="not a LAS/LAZ file")


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_header_claiming_a_trillion_points_is_refused_before_allocating(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"huge{suffix}"
    write_las(path, POINTS, intensity=INTENSITY)
    raw = bytearray(path.read_bytes())
    raw[107:111] = (2**32 - 1).to_bytes(4, "little")  # legacy point count
    path.write_bytes(bytes(raw))
    _assert_format_error(path, match="more than the file's")


def test_laz_chunk_size_beyond_the_points_is_refused_before_lazrs_allocates_it(tmp_path: Path) -> None:
    """Found by the fuzzer: lazrs allocated a damaged chunk size's records (85 GB) and aborted."""
    path = tmp_path / "chunks.laz"
    write_las(path, POINTS, intensity=INTENSITY)
    raw = bytearray(path.read_bytes())
    header_size = int.from_bytes(raw[94:96], "little")
    assert raw[header_size + 2 : header_size + 16] == b"laszip encoded"  # the first record is LASzip's
    chunk_size_at = header_size + 54 + 12
    assert int.from_bytes(raw[chunk_size_at : chunk_size_at + 4], "little") == 50_000
    raw[chunk_size_at : chunk_size_at + 4] = (2**32 - 61).to_bytes(4, "little")
    path.write_bytes(bytes(raw))
    _assert_format_error(path, match="LAZ chunk size of 4,294,967,235 points is damaged")


def test_e57_broken(tmp_path: Path) -> None:
    path = tmp_path / "cut.e57"
    write_e57(path, POINTS)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    _assert_format_error(path, match="cannot read as E57")


def test_e57_pose_applied_and_scans_merged(tmp_path: Path) -> None:
    import pye57

    from slam6d.geometry import invert, rotation_to_quaternion, transform_points

    pose_a = pose_from_xyzrpy(2.0, 1.0, 0.0, 0.0, 0.0, 0.4)
    pose_b = pose_from_xyzrpy(-1.0, 3.0, 0.2, 0.05, 0.0, -0.7)
    a, b = POINTS[:50], POINTS[50:120]
    path = tmp_path / "two.e57"
    e57 = pye57.E57(str(path), mode="w")
    for pts, pose in ((a, pose_a), (b, pose_b)):
        data = {"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2]}
        e57.write_scan_raw(data, rotation=rotation_to_quaternion(pose[:3, :3]), translation=pose[:3, 3])
    e57.close()
    scan = read_scan(path)
    np.testing.assert_allclose(scan.pose, pose_a, atol=1e-9)
    expected = np.vstack([a, transform_points(invert(pose_a) @ pose_b, b)])
    np.testing.assert_allclose(scan.points, expected, atol=1e-4)


def test_vtk_ascii_non_number_names_line(tmp_path: Path) -> None:
    # Coordinates wrap across lines in legacy VTK; the error must still point at the right line.
    path = _text(
        tmp_path / "bad.vtk",
        "# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n1 2 3 4 5\n6 7 8\nnine\n",
    )
    _assert_format_error(path, line=8, match="field 1 is not a number")


def test_vtk_wrapped_coordinates(tmp_path: Path) -> None:
    path = _text(
        tmp_path / "wrap.vtk",
        "# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS 3 double\n1 2 3 4\n5 6\n7 8 9\n"
        "VERTICES 3 6\n1 0\n1 1\n1 2\n",
    )
    np.testing.assert_allclose(read_scan(path).points, np.arange(1.0, 10.0).reshape(3, 3))


@pytest.mark.parametrize(
    ("text", "line", "match"),
    [
        ("# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n1 2 3\n", 7, "truncated"),
        ("# vtk DataFile Version 3.0\nt\nXML\nDATASET POLYDATA\n", 3, "ASCII or BINARY"),
        ("# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS lots float\n", 5, "bad POINTS"),
        ("# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOLYGONS 1 4\n", 5, "expected a POINTS"),
        ("<VTKFile type='PolyData'>\n", 1, "not a legacy VTK"),
    ],
)
def test_vtk_bad_files(tmp_path: Path, text: str, line: int, match: str) -> None:
    _assert_format_error(_text(tmp_path / "b.vtk", text), line=line, match=match)


def test_vtk_binary_truncated(tmp_path: Path) -> None:
    path = tmp_path / "cut.vtk"
    write_vtk(path, POINTS, binary=True)
    raw = path.read_bytes()
    path.write_bytes(raw[: raw.index(b"POINTS") + 100])
    _assert_format_error(path, match="truncated")


def test_csv_non_number_names_line(tmp_path: Path) -> None:
    path = _text(tmp_path / "bad.csv", "x,y,z,nx,ny,nz\n1,2,3,0,0,1\n1,2,3,0,0,1\n1 , 2 , ?, 0,0,1\n")
    _assert_format_error(path, line=4, match="field 3 is not a number")


def test_csv_header_and_whitespace_variants(tmp_path: Path) -> None:
    named = _text(tmp_path / "n.csv", "nx,ny,nz,z,y,x,intensity\n0,0,1,3,2,1,7\n")
    scan = read_scan(named)
    np.testing.assert_allclose(scan.points, [[1, 2, 3]])
    np.testing.assert_allclose(scan.intensity, [7])
    spaced = _text(tmp_path / "s.csv", "  1.0e+00   2.0e+00  3.0e+00\n 4 5 6\n")
    np.testing.assert_allclose(read_scan(spaced).points, [[1, 2, 3], [4, 5, 6]])
    _assert_format_error(_text(tmp_path / "h.csv", "a,b,c\n1,2,3\n"), line=1, match="no column(s)")
    _assert_format_error(_text(tmp_path / "l.csv", "reading\nn.csv\n"), match="list of clouds")
