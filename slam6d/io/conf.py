"""Stanford range-scan ``.conf`` files (e.g. the bunny's ``bun.conf``) read as a sequence of PLY scans.

Each ``bmesh FILE tx ty tz qx qy qz qw`` line names a scan and its registration; ``camera`` and
other lines are ignored. The scan-to-world transform is ``[R(q)ᵀ | t]`` - the quaternion inverted,
translation as written - which is the variant under which the bunny's views actually align. The
scans are metres with y up, hence the ``Y_UP`` convention. Read a folder holding one ``.conf`` file,
or the ``.conf`` file itself.
"""

from __future__ import annotations

from pathlib import Path

from slam6d.errors import FormatError
from slam6d.geometry import Y_UP, Matrix, make_pose, quaternion_to_rotation
from slam6d.io.ply import read_ply
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import read_file_text


def read_conf(path: Path) -> list[tuple[Path, Matrix]]:
    """(scan file, native world_from_scan) for every ``bmesh`` line, in file order."""
    text = read_file_text(path, "'bmesh FILE tx ty tz qx qy qz qw' lines")
    entries = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0] != "bmesh":
            continue
        if len(fields) != 9:
            raise FormatError(
                path, f"'bmesh' needs a file and 7 numbers (t, q), found {len(fields) - 1} fields", line_no
            )
        try:
            tx, ty, tz, qx, qy, qz, qw = (float(v) for v in fields[2:])
        except ValueError:
            raise FormatError(path, "not a number in the line", line_no) from None
        rotation = quaternion_to_rotation([qw, qx, qy, qz]).T
        entries.append((path.parent / fields[1], make_pose(rotation, [tx, ty, tz])))
    if not entries:
        raise FormatError(path, "no 'bmesh' lines")
    return entries


def _conf_file(path: Path) -> Path | None:
    if path.is_file():
        return path if path.suffix.lower() == ".conf" else None
    found = sorted(path.glob("*.conf"))
    return found[0] if len(found) == 1 else None


def discover_conf(path: Path) -> list[Path]:
    conf = _conf_file(path)
    if conf is None:
        return []
    files = [p for p, _ in read_conf(conf)]
    if missing := [p.name for p in files if not p.is_file()]:
        raise FormatError(conf, f"names scan file(s) that do not exist: {', '.join(missing)}")
    return files


def conf_poses(path: Path, files: list[Path]) -> list[Matrix] | None:
    conf = _conf_file(path)
    return [pose for _, pose in read_conf(conf)] if conf is not None else None


def read_conf_scan(path: Path) -> CloudData:
    """Stanford .conf (bmesh FILE t q) listing PLY scans, metres, y up; pose = [R(q)^T | t]"""
    if path.suffix.lower() == ".conf":
        raise FormatError(path, "a .conf file lists scans; read it (or its folder) as a sequence")
    return read_ply(path)


CONF_FORMAT = register_format(
    ScanFormat(
        "conf",
        read_conf_scan,
        Y_UP,
        discover=discover_conf,
        order_fixed_by=lambda path: f"the index {conf.name}" if (conf := _conf_file(path)) else None,
        sequence_poses=conf_poses,
        index_suffixes=(".conf",),
    )
)
