"""Fuzz every file reader of ``slam6d.io`` with mutated and truncated real files; print what happened.

Each format starts from small seed files - cut from the real data sets where they are present
(``SLAM6D_DATA`` or ``../shared/data``), otherwise written by the project's own writers - and each
input is a seed with one to four mutations: truncation, bit flips, overwritten and inserted bytes
(half of them the characters text formats are made of), deleted ranges, duplicated chunks, and
numbers in the header replaced by extreme ones (10^12 points, -1, NaN, 1e308, 2^32-1). Input number
``i`` of a reader comes from a generator seeded with the reader's name and ``i``, so a run is
repeatable and any input can be made again alone. Every input is read through the same entry point
a user's file takes (:func:`slam6d.io.registry.read_scan`, or the pose/trajectory readers). The
outcome of each input is one of:

- ``ok``: read (the mutation kept the file valid);
- the name of one of the project's own errors (``FormatError``, ``EmptyScanError``...): refused
  with a message naming the file - what a reader must do with a bad file;
- ``UNNAMED <error>``: one of the project's errors whose message names none of the files;
- ``CRASH <exception>``: anything else escaped the reader, or the reading process died (a bug);
- ``HANG``: one input took longer than the time limit;
- ``ALLOC``: one input made the reader allocate more than the memory limit (e.g. trusting a
  header's point count).

How it runs (and why it is fast enough for 10,000 inputs per reader on a busy machine): the inputs
are made in this process and read by one long-lived worker process per reader, which imports and
warms up the reader once, writes each input to tmpfs, and caps its address space before each input
(``RLIMIT_AS`` at its current size plus the limit). This process waits for each answer up to the
time limit and kills the worker on a hang; a worker that died (a native abort or segfault) or was
killed is replaced and the run goes on. The earlier harness - hypothesis' engine drawing each input
and tracemalloc tracing every allocation in one process - spent about five times the CPU per input.

Usage::

    python -m benchmarks.fuzz_readers --inputs 10000 --jobs 2    # the figures in docs/hardening.md
    python -m benchmarks.fuzz_readers --inputs 200 --format ply --keep-failures failures/

The test suite runs a bounded sample (``tests/test_fuzz_readers.py``) and fails on any CRASH,
UNNAMED, HANG or ALLOC.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import random
import re
import resource
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from functools import partial
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.errors import Slam6dError

TIME_LIMIT_S = 30.0  # generous: the machine is shared; a reader that loops forever still trips it
ALLOC_LIMIT_BYTES = 256 << 20  # a seed is < 100 kB: a mutation never justifies this much
TEXT_BYTES = b"0123456789-+.eE \t\n\r,naifNA#"
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
    # applied to most mutated inputs: mends checksums, so inputs reach the parser behind them
    reseal: Callable[[bytes], bytes] | None = None


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
    from slam6d.io.registry import read_scan, read_sequence
    from slam6d.io.uos import read_pose_file
    from slam6d.io.vtk import write_vtk

    points, intensity = _cloud()
    root = _data_root()
    real = root is not None

    scan = read_scan
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
        Target("e57", [_written(lambda p: write_e57(p, points, intensity), "c.e57")], scan, reseal=e57_page_checksums),
        Target(
            "conf", conf, partial(read_sequence, format_name="conf"), (sidecar_ply, Seed("b.ply", sidecar_ply.data))
        ),
        Target("poses", [Seed("poses.txt", kitti_poses), Seed("tum.txt", tum)], read_poses_file),
        Target("g2o", [Seed("graph.g2o", g2o)], read_g2o),
        Target("frames", [Seed("scan000.frames", frames)], read_frames),
    ]


# ------------------------------------------------------------------ mutations

E57_PAGE = 1024


def _crc32c_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
        table.append(crc)
    return table


_CRC32C = _crc32c_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli), the checksum of E57 pages."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc = _CRC32C[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def e57_page_checksums(data: bytes) -> bytes:
    """An E57 file with every whole page's checksum recomputed.

    E57 files are 1,024-byte pages, each ending in the big-endian CRC-32C of its other 1,020 bytes,
    and libE57 checks a page's checksum before it parses anything in it: without this, 9,998 of
    10,000 mutated inputs were refused at the checksum and the XML and binary parsers behind it
    were hardly reached.
    """
    out = bytearray(data)
    for start in range(0, len(out) - E57_PAGE + 1, E57_PAGE):
        end = start + E57_PAGE - 4
        out[end : end + 4] = crc32c(bytes(out[start:end])).to_bytes(4, "big")
    return bytes(out)


MUTATIONS = ("truncate", "flip", "set", "insert", "delete", "duplicate", "number")


def mutated(target: Target, index: int) -> Seed:
    """Input number ``index`` of a reader: one of its seeds with one to four mutations applied.

    Each input has its own random generator seeded by the reader's name and the index, so a run is
    repeatable and any input a report names can be made again on its own, without replaying the
    ones before it.
    """
    rng = random.Random(f"{target.name}:{index}")
    seed = rng.choice(target.seeds)
    data = bytearray(seed.data)
    for _ in range(rng.randint(1, 4)):
        kind = rng.choice(MUTATIONS)
        size = len(data)
        where = rng.randrange(size) if size else 0
        if kind == "truncate":
            del data[where:]
        elif kind == "flip" and size:
            data[where] ^= 1 << rng.randrange(8)
        elif kind == "set" and size:
            data[where] = _byte(rng)
        elif kind == "insert":
            data[where:where] = bytes(_byte(rng) for _ in range(rng.randint(1, 16)))
        elif kind == "delete":
            del data[where : where + rng.randint(1, 64)]
        elif kind == "duplicate":
            data[where:where] = data[where : where + rng.randint(1, 256)]
        elif kind == "number":
            _replace_number(data, rng)
    if target.reseal is not None and rng.random() < 0.75:  # a quarter keep the damage for the checksum to find
        return Seed(seed.name, target.reseal(bytes(data)))
    return Seed(seed.name, bytes(data))


def _byte(rng: random.Random) -> int:
    """Half the time a byte that text formats are made of (digits, signs, separators, the letters
    of nan/inf/e), so mutated text files still get past a reader's "is it text" check and reach
    its parser; the other half any byte."""
    return rng.choice(TEXT_BYTES) if rng.random() < 0.5 else rng.randrange(256)


def _replace_number(data: bytearray, rng: random.Random) -> None:
    """An integer or decimal of the first 2 kB (where headers live) becomes an extreme value, or a
    binary length field an extreme one."""
    spans = [m.span() for m in re.finditer(rb"-?\d+(\.\d+)?", bytes(data[:2048]))]
    if spans and rng.random() < 0.5:
        start, end = rng.choice(spans)
        data[start:end] = rng.choice(EXTREME_NUMBERS)
    elif len(data) >= 8:
        at = rng.randint(0, min(len(data), 2048) - 4)
        width = rng.choice((2, 4, 8))
        data[at : at + width] = (b"\xff" * width)[: len(data) - at]


# ------------------------------------------------------------------ reading one input


def read_outcome(target: Target, seed: Seed, folder: Path) -> str:
    """Read one input in this process; the outcome's name (see the module docstring).

    A ``MemoryError`` is ``ALLOC``: in a worker the address space is capped per input, so an
    allocation past the limit fails there rather than swapping the machine. A refusal whose message
    names none of the files it was given is reported too (``UNNAMED``): the user could not tell
    which file to fix.
    """
    for sidecar in target.sidecars:
        (folder / sidecar.name).write_bytes(sidecar.data)
    path = folder / seed.name
    path.write_bytes(seed.data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            target.read(path)
        return "ok"
    except MemoryError:
        return "ALLOC"
    except Slam6dError as exc:
        names = [seed.name, *(sidecar.name for sidecar in target.sidecars)]
        if not any(name in str(exc) for name in names):
            return f"UNNAMED {type(exc).__name__}: {str(exc)[:120]}"
        return type(exc).__name__
    except Exception as exc:  # a reader bug: reported, not raised, so the counts cover every input
        return f"CRASH {type(exc).__name__}: {str(exc)[:120]}"
    finally:
        for file in folder.iterdir():
            file.unlink()


def _address_space_bytes() -> int:
    """This process's virtual memory size (what ``RLIMIT_AS`` limits)."""
    with open("/proc/self/statm", "rb") as stream:
        return int(stream.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def _scratch_root() -> str | None:
    """tmpfs when there is one: inputs are written and deleted 10,000 times per reader."""
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def serve(inbox_fd: int, outbox_fd: int) -> None:
    """The worker's loop: read the inputs the parent sends, answer each with its outcome.

    One long-lived process reads many inputs (importing numpy and the readers, and compiling the
    numba parsers, costs seconds; a process per input would spend most of the run on that). Before
    each input the address space is capped at its current size plus the allocation limit, so an
    input that makes a reader allocate more fails with ``MemoryError`` (or kills the process, for
    native code that aborts on a failed allocation); the parent reports both as ``ALLOC``. The
    parent enforces the time limit by killing this process, which also stops native loops that a
    signal handler in Python could not interrupt.
    """
    os.dup2(2, 1)  # anything a reader or a native library prints goes to the log, not the channel
    inbox, outbox = Connection(inbox_fd, writable=False), Connection(outbox_fd, readable=False)
    read, seeds, sidecars, alloc_limit = inbox.recv()
    target = Target("worker", [Seed(*seed) for seed in seeds], read, tuple(Seed(*sidecar) for sidecar in sidecars))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with tempfile.TemporaryDirectory(prefix="fuzz-", dir=_scratch_root()) as scratch:
        folder = Path(scratch)
        for seed in target.seeds:  # imports and compiles the reader before the limited inputs
            read_outcome(target, seed, folder)
        outbox.send("ready")
        while (message := inbox.recv()) is not None:
            seed = Seed(*message)
            cap = _address_space_bytes() + alloc_limit
            resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else min(cap, hard), hard))
            try:
                result = read_outcome(target, seed, folder)
            finally:
                resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
            outbox.send(result)


# ------------------------------------------------------------------ the parent's side


@dataclass(frozen=True)
class Limits:
    """What makes an input a failure besides an exception that is not the project's own."""

    seconds: float = TIME_LIMIT_S
    alloc_bytes: int = ALLOC_LIMIT_BYTES
    start_seconds: float = 600.0  # a worker's imports and warm-up reads, on a loaded machine


ALLOC_SIGNS = ("memory allocation of", "bad_alloc", "MemoryError", "Cannot allocate memory", "out of memory")


class Worker:
    """A long-lived reading process for one reader, restarted only after it hung or died."""

    def __init__(self, target: Target, limits: Limits, scratch: Path) -> None:
        self.target = target
        self.limits = limits
        self.log_path = scratch / "worker.log"  # its stdout and stderr, read when it dies
        self.restarts = 0
        self._process: subprocess.Popen[bytes] | None = None
        self._inbox: Connection | None = None
        self._outbox: Connection | None = None

    def _start(self) -> None:
        from_parent, to_worker = os.pipe()  # (read end, write end)
        from_worker, to_parent = os.pipe()
        code = "import sys; from benchmarks.fuzz_readers import serve; serve(int(sys.argv[1]), int(sys.argv[2]))"
        with open(self.log_path, "wb") as log:
            self._process = subprocess.Popen(
                [sys.executable, "-c", code, str(from_parent), str(to_parent)],
                pass_fds=(from_parent, to_parent),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                env=_worker_environment(),
            )
        os.close(from_parent)
        os.close(to_parent)
        self._outbox = Connection(to_worker, readable=False)
        self._inbox = Connection(from_worker, writable=False)
        plain = (_plain(self.target.seeds), _plain(self.target.sidecars))
        self._outbox.send((self.target.read, *plain, self.limits.alloc_bytes))
        if not self._inbox.poll(self.limits.start_seconds) or self._receive() != "ready":
            tail = self._log_tail()
            self.close()
            raise RuntimeError(f"the {self.target.name} reader's worker did not start: {tail}")

    def _receive(self) -> str | None:
        assert self._inbox is not None
        try:
            answer: str = self._inbox.recv()
        except (EOFError, OSError):
            return None
        return answer

    def outcome(self, seed: Seed) -> str:
        """Read one input in the worker; ``HANG`` if it takes over the time limit, ``ALLOC`` or
        ``CRASH`` if the worker died on it (a native abort or segfault)."""
        if self._process is None:
            self._start()
        assert self._outbox is not None and self._inbox is not None
        try:
            self._outbox.send((seed.name, seed.data))
        except OSError:
            return self._died()
        if not self._inbox.poll(self.limits.seconds):
            self.close()
            self.restarts += 1
            return "HANG"
        answer = self._receive()
        return self._died() if answer is None else answer

    def _died(self) -> str:
        assert self._process is not None
        code = self._process.wait()
        lines = self._log_tail().splitlines()
        self.close()
        self.restarts += 1
        if any(sign in line for line in lines for sign in ALLOC_SIGNS):
            return "ALLOC"
        how = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit status {code}"
        return f"CRASH the reading process died ({how}){': ' + lines[0][:120] if lines else ''}"

    def _log_tail(self) -> str:
        """The end of the worker's output: what a native library said before it aborted."""
        try:
            return self.log_path.read_bytes()[-65536:].decode(errors="replace").strip()
        except OSError:
            return ""

    def close(self) -> None:
        """Stop the worker (politely: it exits at the end of its input stream; a hung one is killed)."""
        if self._outbox is not None:
            with contextlib.suppress(OSError):
                self._outbox.send(None)
            self._outbox.close()
        if self._inbox is not None:
            self._inbox.close()
        if self._process is not None:
            try:
                self._process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._process, self._inbox, self._outbox = None, None, None


def _plain(seeds: Sequence[Seed]) -> list[tuple[str, bytes]]:
    """Seeds as tuples: the parent may run as ``__main__``, whose classes a worker cannot unpickle."""
    return [(seed.name, seed.data) for seed in seeds]


def _worker_environment() -> dict[str, str]:
    """The parent's environment, its module search path (so a worker imports the same code, even
    readers defined in a test module) and single-threaded numeric libraries (a thread pool would
    reserve address space the per-input cap counts, and the machine running a fuzz run is
    usually busy)."""
    path = [os.getcwd() if entry == "" else entry for entry in sys.path]
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(entry for entry in path if Path(entry).is_dir()),
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "MALLOC_ARENA_MAX": "2",
    }


def fuzz(
    target: Target,
    inputs: int,
    on_input: Callable[[int, Seed, str], None] | None = None,
    limits: Limits = Limits(),
) -> Counter[str]:
    """Feed ``inputs`` mutated files (numbers ``0 .. inputs - 1``) to one reader; counts per outcome."""
    counts: Counter[str] = Counter()
    with tempfile.TemporaryDirectory(prefix="fuzz-", dir=_scratch_root()) as scratch:
        worker = Worker(target, limits, Path(scratch))
        try:
            for index in range(inputs):
                seed = mutated(target, index)
                result = worker.outcome(seed)
                counts[result] += 1
                if on_input is not None:
                    on_input(index, seed, result)
        finally:
            worker.close()
    return counts


def is_failure(outcome: str) -> bool:
    return outcome.startswith(("CRASH", "UNNAMED")) or outcome in ("HANG", "ALLOC")


def report(target: Target, inputs: int, keep_failures: Path | None) -> tuple[str, int]:
    """Fuzz one reader: its table row (with one line per kind of failure below it) and its failures."""
    began = time.perf_counter()

    def on_input(index: int, seed: Seed, result: str) -> None:
        if keep_failures is not None and is_failure(result):
            keep_failures.mkdir(parents=True, exist_ok=True)
            (keep_failures / f"{target.name.replace(' ', '_')}-{index}-{seed.name}").write_bytes(seed.data)
        if (index + 1) % 1000 == 0:
            print(f"{target.name}: {index + 1:,}/{inputs:,}", file=sys.stderr, flush=True)

    counts = fuzz(target, inputs, on_input)
    bad = {k: v for k, v in counts.items() if is_failure(k)}
    refused = {k: v for k, v in counts.items() if k != "ok" and not is_failure(k)}
    crashes = sum(v for k, v in bad.items() if k.startswith("CRASH"))
    unnamed = sum(v for k, v in bad.items() if k.startswith("UNNAMED"))
    row = (
        f"{target.name:10} {sum(counts.values()):7,} {counts['ok']:6,} {sum(refused.values()):8,} {crashes:6,} "
        f"{unnamed:8,} {counts['HANG']:5,} {counts['ALLOC']:6,} {time.perf_counter() - began:7.1f}  "
        + ", ".join(f"{k} {v:,}" for k, v in sorted(refused.items()))
    )
    lines = [row, *(f"    {count:6,} x {kind}" for kind, count in sorted(bad.items()))]
    return "\n".join(lines), sum(bad.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=10_000, help="mutated inputs per reader")
    parser.add_argument("--format", action="append", help="only these readers (repeatable)")
    parser.add_argument("--jobs", type=int, default=1, help="readers fuzzed at the same time (one worker each)")
    parser.add_argument("--keep-failures", type=Path, help="write every failing input into this folder")
    args = parser.parse_args()
    chosen = [t for t in targets() if not args.format or t.name in args.format]
    print(f"{args.inputs:,} inputs per reader; seeds from {'real data + writers' if _data_root() else 'writers'}")
    print(
        f"{'reader':10} {'inputs':>7} {'ok':>6} {'refused':>8} {'crash':>6} {'unnamed':>8} {'hang':>5} {'alloc':>6} "
        f"{'s':>7}  refusals",
        flush=True,
    )
    failures = 0
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:  # each thread only waits on its worker process
        for future in as_completed([pool.submit(report, t, args.inputs, args.keep_failures) for t in chosen]):
            lines, failed = future.result()
            failures += failed
            print(lines, flush=True)
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
