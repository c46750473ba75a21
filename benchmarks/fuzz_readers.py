"""Fuzz every file reader of ``slam6d.io`` with mutated and truncated real files; print what happened.

Each format starts from small seed files - cut from the real data sets where they are present
(``SLAM6D_DATA`` or ``../shared/data``), otherwise written by the project's own writers - and
hypothesis mutates them: truncation, bit flips, overwritten and inserted bytes, deleted ranges,
duplicated chunks, and numbers in the header replaced by extreme ones (10^12 points, -1, NaN,
1e308, 2^32-1). Every input is read through the same entry point a user's file takes
(:func:`slam6d.io.registry.read_scan`, or the pose/trajectory readers). The outcome of each input
is one of:

- ``ok``: read (the mutation kept the file valid);
- the name of one of the project's own errors (``FormatError``, ``EmptyScanError``...): refused
  with a message naming the file - what a reader must do with a bad file;
- ``CRASH <exception>``: anything else escaped the reader (a bug);
- ``HANG``: one input took longer than the time limit;
- ``ALLOC``: one input made the reader allocate more than the memory limit (e.g. trusting a
  header's point count).

Usage::

    python -m benchmarks.fuzz_readers --inputs 10000        # the figures in docs/fuzzing.md
    python -m benchmarks.fuzz_readers --inputs 200 --format ply

The test suite runs a bounded sample (``tests/test_fuzz_readers.py``) and fails on any CRASH,
HANG or ALLOC.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import sys
import tempfile
import time
import tracemalloc
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from slam6d.errors import Slam6dError

TIME_LIMIT_S = 30.0  # generous: the machine is shared; a reader that loops forever still trips it
ALLOC_LIMIT_BYTES = 256 << 20  # a seed is < 100 kB: a mutation never justifies this much
EXTREME_NUMBERS = (b"1000000000000", b"4294967295", b"18446744073709551615", b"-1", b"0", b"nan", b"1e308", b"-0")


@dataclass(frozen=True)
class Seed:
    name: str  # file name, whose suffix picks the format
    data: bytes


@dataclass(frozen=True)
class Target:
    """One reader: its seed files and how a file is read."""

    name: str
    seeds: list[Seed]
    read: Callable[[Path], Any]
    sidecars: tuple[Seed, ...] = ()  # files written beside every input unmutated (e.g. the PLYs a .conf lists)


# ------------------------------------------------------------------ seeds


def _data_root() -> Path | None:
    for candidate in (os.environ.get("SLAM6D_DATA"), Path(__file__).resolve().parents[2] / "shared" / "data"):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


def _cloud(count: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(-5.0, 5.0, (count, 3)), rng.uniform(0.0, 1.0, count).astype(np.float32)


def _written(writer: Callable[[Path], None], name: str) -> Seed:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / name
        writer(path)
        return Seed(name, path.read_bytes())


def _head_lines(path: Path, lines: int) -> bytes:
    with open(path, "rb") as stream:
        return b"".join(stream.readline() for _ in range(lines))


def _ply_head(path: Path, vertices: int) -> bytes:
    """An ASCII PLY cut to its first ``vertices`` vertices, its header count edited to match."""
    raw = path.read_bytes()
    end = raw.index(b"\n", raw.index(b"end_header")) + 1
    header = re.sub(rb"element vertex \d+", b"element vertex %d" % vertices, raw[:end])
    header = re.sub(rb"element face \d+", b"element face 0", header)
    body = b"".join(raw[end:].splitlines(keepends=True)[:vertices])
    return header + body


def targets() -> list[Target]:
    from slam6d.io.e57 import write_e57
    from slam6d.io.frames import read_frames
    from slam6d.io.las import write_las
    from slam6d.io.pcd import write_pcd
    from slam6d.io.ply import write_ply
    from slam6d.io.poses import read_g2o, read_poses_file
    from slam6d.io.registry import read_scan
    from slam6d.io.uos import read_pose_file
    from slam6d.io.vtk import write_vtk

    points, intensity = _cloud()
    root = _data_root()
    real = root is not None

    def scan(path: Path) -> Any:
        return read_scan(path)

    uos = [Seed("scan000.3d", b"".join(f"{x:.2f} {y:.2f} {z:.2f}\n".encode() for x, y, z in points * 100))]
    ply = [
        _written(lambda p: write_ply(p, points, intensity=intensity), "binary.ply"),
        _written(lambda p: write_ply(p, points, binary=False), "ascii.ply"),
    ]
    kitti = [Seed("000000.bin", np.column_stack([points, intensity]).astype(np.float32).tobytes())]
    vtk = [
        _written(lambda p: write_vtk(p, points), "ascii.vtk"),
        _written(lambda p: write_vtk(p, points, True), "b.vtk"),
    ]
    csv = [Seed("cloud.csv", b"x,y,z\n" + b"".join(b"%.4f,%.4f,%.4f\n" % tuple(p) for p in points))]
    conf = [Seed("scans.conf", b"camera 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\nbmesh b.ply 0.1 0 0 0 0 0.1 1\n")]
    if real:
        assert root is not None
        uos.append(Seed("scan001.3d", _head_lines(root / "kurt3d_3dtk" / "scan000.3d", 300)))
        ply.append(Seed("bun000.ply", _ply_head(root / "stanford_bunny" / "bun000.ply", 300)))
        bins = sorted((root / "balm_hall" / "velodyne_style_bin").glob("*.bin"))
        kitti.append(Seed("000001.bin", bins[0].read_bytes()[: 300 * 16]))
        vtk.append(Seed("cloud.vtk", (root / "libpointmatcher_pairs" / "cloud.00000.vtk").read_bytes()[:20000]))
        csv.append(Seed("car.csv", _head_lines(root / "libpointmatcher_pairs" / "car_cloud400.csv", 300)))
        conf.append(Seed("bun.conf", (root / "stanford_bunny" / "bun.conf").read_bytes()))
    pcd = [
        _written(lambda p: write_pcd(p, points, intensity), "binary.pcd"),
        _written(lambda p: write_pcd(p, points, intensity, binary=False), "ascii.pcd"),
    ]
    with contextlib.suppress(ImportError):
        import open3d as o3d  # only a peer in the benchmarks: it writes LZF-compressed bodies

        def compressed(path: Path) -> None:
            cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(np.float32)))  # type: ignore[call-overload]
            o3d.t.io.write_point_cloud(str(path), cloud, compressed=True)  # type: ignore[arg-type]

        pcd.append(_written(compressed, "compressed.pcd"))
    sidecar_ply = _written(lambda p: write_ply(p, points[:50], binary=False), "a.ply")
    kitti_poses = b"".join(b"1 0 0 %d 0 1 0 0 0 0 1 0\n" % k for k in range(5))
    tum = b"".join(b"%d.0 %d 0 0 0 0 0 1\n" % (k, k) for k in range(5))
    g2o = (
        b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        b"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + b" ".join([b"1"] + [b"0"] * 5 + [b"1"] + [b"0"] * 4 + [b"1"] * 1) + b"\n"
    )
    frames = b"".join(b"1 0 0 0 0 1 0 0 0 0 1 0 %d 0 0 1 2\n" % k for k in range(3))
    return [
        Target("uos", uos, scan, (Seed("scan000.pose", b"10 0 20\n0 15 0\n"),)),
        Target("uos pose", [Seed("scan000.pose", b"10.5 -3 20\n0 15.25 1\n")], read_pose_file),
        Target("kitti", kitti, scan),
        Target("ply", ply, scan),
        Target("pcd", pcd, scan),
        Target("xyz", [Seed("cloud.xyz", b"".join(b"%.3f %.3f %.3f\n" % tuple(p) for p in points))], scan),
        Target("csv", csv, scan),
        Target("vtk", vtk, scan),
        Target("las", [_written(lambda p: write_las(p, points, intensity=intensity), "c.las")], scan),
        Target("laz", [_written(lambda p: write_las(p, points, intensity=intensity), "c.laz")], scan),
        Target("e57", [_written(lambda p: write_e57(p, points, intensity), "c.e57")], scan),
        Target("conf", conf, _read_conf_sequence, (sidecar_ply, Seed("b.ply", sidecar_ply.data))),
        Target("poses", [Seed("poses.txt", kitti_poses), Seed("tum.txt", tum)], read_poses_file),
        Target("g2o", [Seed("graph.g2o", g2o)], read_g2o),
        Target("frames", [Seed("scan000.frames", frames)], read_frames),
    ]


def _read_conf_sequence(path: Path) -> Any:
    from slam6d.io.registry import read_sequence

    return read_sequence(path, "conf")


# ------------------------------------------------------------------ mutations


@st.composite
def mutated(draw: st.DrawFn, seeds: list[Seed]) -> Seed:
    """A seed with one to four mutations applied."""
    seed = draw(st.sampled_from(seeds))
    data = bytearray(seed.data)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(("truncate", "flip", "set", "insert", "delete", "duplicate", "number")))
        size = len(data)
        where = draw(st.integers(0, max(size - 1, 0)))
        if kind == "truncate":
            del data[where:]
        elif kind == "flip" and size:
            data[where] ^= 1 << draw(st.integers(0, 7))
        elif kind == "set" and size:
            data[where] = draw(st.integers(0, 255))
        elif kind == "insert":
            data[where:where] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "delete":
            del data[where : where + draw(st.integers(1, 64))]
        elif kind == "duplicate":
            data[where:where] = data[where : where + draw(st.integers(1, 256))]
        elif kind == "number":
            _replace_number(data, draw)
    return Seed(seed.name, bytes(data))


def _replace_number(data: bytearray, draw: st.DrawFn) -> None:
    """An integer or decimal of the first 2 kB (where headers live) becomes an extreme value, or a
    binary length field an extreme one."""
    head = bytes(data[:2048])
    spans = [m.span() for m in re.finditer(rb"-?\d+(\.\d+)?", head)]
    in_text: bool = draw(st.booleans())
    if spans and in_text:
        start, end = draw(st.sampled_from(spans))
        data[start:end] = draw(st.sampled_from(EXTREME_NUMBERS))
    elif len(data) >= 8:
        at = draw(st.integers(0, min(len(data), 2048) - 4))
        width = draw(st.sampled_from((2, 4, 8)))
        data[at : at + width] = (b"\xff" * width)[: len(data) - at]


# ------------------------------------------------------------------ running


class _TimeoutError(Exception):
    pass


@contextlib.contextmanager
def _time_limit(seconds: float) -> Iterator[None]:
    def expire(signum: int, frame: Any) -> None:
        raise _TimeoutError

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def outcome_of(target: Target, seed: Seed, folder: Path) -> str:
    """Read one input; the outcome's name (see the module docstring)."""
    for sidecar in target.sidecars:
        (folder / sidecar.name).write_bytes(sidecar.data)
    path = folder / seed.name
    path.write_bytes(seed.data)
    tracemalloc.reset_peak()
    try:
        with _time_limit(TIME_LIMIT_S), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            target.read(path)
        result = "ok"
    except _TimeoutError:
        result = "HANG"
    except Slam6dError as exc:
        result = type(exc).__name__
    except Exception as exc:  # a reader bug: reported, not raised, so the counts cover every input
        result = f"CRASH {type(exc).__name__}: {str(exc)[:120]}"
    finally:
        for file in folder.iterdir():
            file.unlink()
    if tracemalloc.get_traced_memory()[1] > ALLOC_LIMIT_BYTES and not result.startswith("CRASH"):
        result = "ALLOC"
    return result


def fuzz(target: Target, inputs: int, on_input: Callable[[Seed, str], None] | None = None) -> Counter[str]:
    """Feed ``inputs`` mutated files to one reader; counts per outcome."""
    counts: Counter[str] = Counter()
    with tempfile.TemporaryDirectory(prefix="fuzz-") as scratch:
        folder = Path(scratch)

        @settings(
            max_examples=inputs,
            phases=[Phase.generate],
            database=None,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
        )
        @given(mutated(target.seeds))
        def run(seed: Seed) -> None:
            result = outcome_of(target, seed, folder)
            counts[result] += 1
            if on_input is not None:
                on_input(seed, result)

        for seed in target.seeds:  # imports and compiles the reader outside the timed, traced inputs
            outcome_of(target, seed, folder)
        started = tracemalloc.is_tracing()
        if not started:
            tracemalloc.start()
        try:
            run()
        finally:
            if not started:
                tracemalloc.stop()
    return counts


def is_failure(outcome: str) -> bool:
    return outcome.startswith("CRASH") or outcome in ("HANG", "ALLOC")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=10_000, help="mutated inputs per reader")
    parser.add_argument("--format", action="append", help="only these readers (repeatable)")
    parser.add_argument("--keep-failures", type=Path, help="write every failing input into this folder")
    args = parser.parse_args()
    chosen = [t for t in targets() if not args.format or t.name in args.format]
    print(f"{args.inputs:,} inputs per reader; seeds from {'real data + writers' if _data_root() else 'writers'}")
    print(
        f"{'reader':10} {'inputs':>7} {'ok':>6} {'refused':>8} {'crash':>6} {'hang':>5} {'alloc':>6} {'s':>6}  refusals"
    )
    failures = 0
    for target in chosen:
        began = time.perf_counter()

        def keep(seed: Seed, result: str, target: Target = target) -> None:
            if args.keep_failures and is_failure(result):
                args.keep_failures.mkdir(parents=True, exist_ok=True)
                index = len(list(args.keep_failures.iterdir()))
                (args.keep_failures / f"{target.name.replace(' ', '_')}-{index}-{seed.name}").write_bytes(seed.data)

        counts = fuzz(target, args.inputs, keep)
        bad = {k: v for k, v in counts.items() if is_failure(k)}
        failures += sum(bad.values())
        refused = {k: v for k, v in counts.items() if k != "ok" and not is_failure(k)}
        print(
            f"{target.name:10} {sum(counts.values()):7,} {counts['ok']:6,} {sum(refused.values()):8,} "
            f"{sum(v for k, v in bad.items() if k.startswith('CRASH')):6,} {counts['HANG']:5,} {counts['ALLOC']:6,} "
            f"{time.perf_counter() - began:6.1f}  {', '.join(f'{k} {v}' for k, v in sorted(refused.items()))}"
        )
        for kind, count in sorted(bad.items()):
            print(f"    {count:6,} x {kind}")
        sys.stdout.flush()
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
