"""One registry of scan formats, so every command takes the same ``--format`` names.

A format module registers a :class:`ScanFormat`: how to read one file into native coordinates,
which frame convention those coordinates use, and (optionally) how to find and order the scans
of a directory. Everything common - dropping NaN/inf with a warning, range filtering, refusing
empty scans, converting to the canonical frame - happens here once.
"""

from __future__ import annotations

import inspect
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import EmptyScanError, FormatError, InvalidValueError
from slam6d.geometry import CANONICAL, FrameConvention, Matrix, check_rigid
from slam6d.io.order import DEFAULT_ORDER, check_order, sort_scan_files
from slam6d.scan import Scan, ScanSequence


@dataclass
class CloudData:
    """What a reader returns for one file: native units and frame, nothing filtered yet."""

    points: NDArray[np.float64]
    intensity: NDArray[np.float32] | None = None
    pose: Matrix | None = None  # native world_from_scan if the file (or its sidecar) carries one


@dataclass(frozen=True)
class ScanFormat:
    """A registered format. Each registration states only what differs from the common case: a file
    suffix that is the format's name (``.ply``), canonical metres with z up, a description that is the
    first paragraph of the reader's docstring (so the text ``slam6d formats`` prints is kept where the
    reader is written), and a plain folder listing."""

    name: str
    read: Callable[[Path], CloudData]
    convention: FrameConvention = CANONICAL
    suffixes: tuple[str, ...] = ()  # () means ``(".<name>",)``
    description: str = ""  # "" means the first paragraph of ``read``'s docstring
    # Lists the scan files of a directory in acquisition order; default: every file with a suffix, in
    # natural order (slam6d.io.order).
    discover: Callable[[Path], list[Path]] | None = None
    # Poses for a whole directory (e.g. a KITTI poses file beside the scans), native frame, or None.
    sequence_poses: Callable[[Path, list[Path]], list[Matrix] | None] | None = None
    # Suffixes of files that list a sequence (e.g. Stanford ``.conf``): read_sequence on such a file
    # passes it to discover/sequence_poses in place of a directory.
    index_suffixes: tuple[str, ...] = ()
    # What fixes the order of a directory's scans when it is not a plain folder listing (an index file,
    # a numbering scheme), or None; ``--order`` other than natural is refused then (see slam6d.io.order).
    order_fixed_by: Callable[[Path], str | None] | None = None

    def __post_init__(self) -> None:
        if not self.suffixes:
            object.__setattr__(self, "suffixes", (f".{self.name}",))
        if not self.description:
            object.__setattr__(self, "description", _first_paragraph(self.read))


def _first_paragraph(function: Callable[..., object]) -> str:
    doc = inspect.getdoc(function) or ""
    return " ".join(doc.split("\n\n", 1)[0].split())


class NonFinitePointsWarning(UserWarning):
    """Some points were NaN or infinite and were dropped."""


_FORMATS: dict[str, ScanFormat] = {}


def register_format(fmt: ScanFormat) -> ScanFormat:
    _FORMATS[fmt.name] = fmt
    return fmt


def format_names() -> list[str]:
    _load_builtin_formats()
    return sorted(_FORMATS)


def get_format(name: str) -> ScanFormat:
    _load_builtin_formats()
    try:
        return _FORMATS[name]
    except KeyError:
        raise FormatError(name, f"unknown format '{name}'; known formats: {', '.join(sorted(_FORMATS))}") from None


def detect_format(path: Path) -> ScanFormat:
    """Guess the format from a file's suffix or a directory's contents."""
    _load_builtin_formats()
    path = Path(path)
    if path.is_dir():
        # Fixed priority, not import order: a folder of KITTI bins with a stray .csv must stay KITTI.
        ranked = sorted(_FORMATS.values(), key=lambda f: _priority(f.name))
        for fmt in ranked:
            if fmt.discover is not None and fmt.discover(path):
                return fmt
        for fmt in ranked:
            if any(p.suffix.lower() in fmt.suffixes for p in path.iterdir()):
                return fmt
        raise FormatError(path, "no scan files of a known format in this directory; pass --format")
    suffix = "".join(path.suffixes[-1:]).lower()
    for fmt in _FORMATS.values():
        if suffix in fmt.suffixes:
            return fmt
    raise FormatError(
        path, f"cannot tell the format from suffix '{suffix}'; pass --format ({', '.join(sorted(_FORMATS))})"
    )


def resolve_format(path: Path, format_name: str | None) -> ScanFormat:
    return get_format(format_name) if format_name else detect_format(path)


@dataclass(frozen=True)
class ReadOptions:
    """Filters applied to every scan, in native units (as the user knows their scanner)."""

    min_range: float | None = None
    max_range: float | None = None


def clean_points(path: Path, cloud: CloudData, options: ReadOptions) -> CloudData:
    """Drop non-finite points (with a warning) and range-filter; refuse a scan with nothing left."""
    points = np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        raise EmptyScanError(path, "the file contains no points")
    ranged = options.min_range is not None or options.max_range is not None
    if np.isfinite(points).all() and not ranged:
        return CloudData(points, cloud.intensity, cloud.pose)  # the usual case: nothing to drop, no copy
    finite = np.asarray(np.isfinite(points).all(axis=1))
    dropped = int((~finite).sum())
    if dropped:
        warnings.warn(f"{path}: dropped {dropped} NaN/inf point(s)", NonFinitePointsWarning, stacklevel=3)
    keep = finite
    if ranged:
        safe = np.where(finite[:, None], points, 0.0)
        ranges = np.sqrt(np.einsum("ij,ij->i", safe, safe))
        if options.min_range is not None:
            keep &= ranges >= options.min_range
        if options.max_range is not None:
            keep &= ranges <= options.max_range
    if not keep.any():
        raise EmptyScanError(path, f"all {points.shape[0]} points were non-finite or outside the range filter")
    intensity = cloud.intensity[keep] if cloud.intensity is not None else None
    return CloudData(points[keep], intensity, cloud.pose)


def read_scan(
    path: Path | str,
    format_name: str | None = None,
    options: ReadOptions = ReadOptions(),
    convention: FrameConvention | None = None,
) -> Scan:
    """Read one scan file into the canonical frame."""
    path = Path(path)
    if not path.exists():
        raise FormatError(path, "no such file")
    fmt = resolve_format(path, format_name)
    cloud = clean_points(path, fmt.read(path), options)
    conv = convention or fmt.convention
    pose = conv.pose_to_canonical(rigid_pose(path, cloud.pose)) if cloud.pose is not None else np.eye(4)
    intensity = None if cloud.intensity is None else np.asarray(cloud.intensity, dtype=np.float32)
    return Scan(
        conv.points_to_canonical(cloud.points),
        pose,
        name=path.stem,
        source=path,
        intensity=intensity,
        has_pose=cloud.pose is not None,
    )


def rigid_pose(path: Path, pose: Matrix, scan: str | None = None) -> Matrix:
    """A pose a file carries, checked rigid (:func:`slam6d.geometry.check_rigid`), else a
    :class:`FormatError` naming the file: a scaled or sheared pose would be stored and break every
    export and solver downstream."""
    try:
        return check_rigid(pose, f"pose of {scan}" if scan else "pose")
    except InvalidValueError as exc:
        raise FormatError(path, str(exc)) from None


def list_scan_files(path: Path, fmt: ScanFormat, order: str = DEFAULT_ORDER) -> list[Path]:
    """The scan files of a directory (or index file) in acquisition order.

    Folder listings come in natural order (``2.pcd`` before ``10.pcd``); ``order`` = ``name`` or
    ``mtime`` re-sorts them. A format whose order an index fixes refuses anything but the default.
    """
    check_order(order)
    if fmt.discover is not None:
        files = fmt.discover(path)
    else:
        files = sort_scan_files(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in fmt.suffixes)
    files = [f for f in files if _inside(f, path)]
    if not files:
        raise FormatError(path, f"no '{fmt.name}' scans found in this directory")
    if order != DEFAULT_ORDER:
        fixed_by = fmt.order_fixed_by(path) if fmt.order_fixed_by is not None else None
        if fixed_by is not None:
            raise FormatError(path, f"the scan order is fixed by {fixed_by}; --order {order} does not apply")
        files = sort_scan_files(files, order)
    return files


def _inside(file: Path, folder: Path) -> bool:
    """A listed scan must be the folder's own: a symbolic link leading out of it is left out, so a
    session over a folder never lists or reads files elsewhere on the machine."""
    if not file.is_symlink():
        return True
    base = folder.resolve() if folder.is_dir() else folder.resolve().parent
    return file.resolve().is_relative_to(base)


def read_sequence(
    path: Path | str,
    format_name: str | None = None,
    options: ReadOptions = ReadOptions(),
    first: int = 0,
    last: int | None = None,
    poses_file: Path | None = None,
    convention: FrameConvention | None = None,
    progress: Callable[[int, int], None] | None = None,
    order: str = DEFAULT_ORDER,
) -> ScanSequence:
    """Read a directory of scans (or a single file, or a sequence index file) in acquisition order.

    ``order`` is how a folder's files are sorted (:mod:`slam6d.io.order`: natural by default).

    ``poses_file`` (KITTI 3x4, TUM or 4x4 lines, native frame) overrides any poses the scans carry, which is
    how odometry is supplied for formats that have none.
    """
    path = Path(path)
    if not path.exists():
        raise FormatError(path, "no such file or directory")
    fmt = resolve_format(path, format_name)
    listing = path.is_dir() or path.suffix.lower() in fmt.index_suffixes
    all_files = list_scan_files(path, fmt, order) if listing else [path]
    stop = None if last is None else last + 1
    files = all_files[first:stop]
    conv = convention or fmt.convention
    scans = []
    for index, file in enumerate(files):
        scans.append(read_scan(file, fmt.name, options, conv))
        if progress is not None:
            progress(index + 1, len(files))
    # External poses are aligned with every scan of the directory, before --first/--last slicing.
    external: list[Matrix] | None = None
    if poses_file is not None:
        from slam6d.io.poses import read_poses_file

        external = read_poses_file(poses_file)
    elif fmt.sequence_poses is not None and listing:
        external = fmt.sequence_poses(path, all_files)
    if external is not None:
        if len(external) < len(all_files):
            raise FormatError(poses_file or path, f"{len(external)} poses for {len(all_files)} scans")
        for scan, native in zip(scans, external[first:stop], strict=True):
            scan.pose = conv.pose_to_canonical(rigid_pose(poses_file or path, native, scan.name))
            scan.has_pose = True
    return ScanSequence(scans, conv, path, fmt.name)


_LOADED = False
# Also the order in which a folder's format is guessed: formats with a strict naming scheme first.
_BUILTIN_MODULES = ("uos", "kitti", "ply", "pcd", "xyz", "las", "e57", "vtk", "csv", "conf")


def _priority(name: str) -> int:
    return _BUILTIN_MODULES.index(name) if name in _BUILTIN_MODULES else len(_BUILTIN_MODULES)


def _load_builtin_formats() -> None:
    """Import the format modules once; each registers itself on import."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    import importlib

    for module in _BUILTIN_MODULES:
        try:
            importlib.import_module(f"slam6d.io.{module}")
        except ModuleNotFoundError as exc:  # a format module not written yet, or its library missing
            if exc.name not in (f"slam6d.io.{module}",):
                raise
