"""A long upload must not slow other requests: their latency with and without a slow, large upload.

    .venv/bin/python benchmarks/slow_upload.py [--upload-mb 200] [--rate-mb 20] [--seconds 10] [--pollers 2]

A ``slam6d-workbench`` server runs as its own process (so the clients here do not share its
interpreter) over the tests' corridor session. ``--pollers`` clients poll back to back what a
session page polls (``GET /api/sessions/{id}``, ``GET .../poses``) and the session list:

1. for ``--seconds`` with nothing else going on (the baseline);
2. while one client sends a multipart upload of ``--upload-mb`` MB of valid scan text at
   ``--rate-mb`` MB/s (a slow link: the server spools it as it arrives);
3. while the server parses that upload, from its last byte until the answer (201);
4. for ``--seconds`` after it (the baseline again: how far the machine's own load drifted).

One more client polls a path no route has (404): answered on the event loop itself, with no worker
thread, its latency shows whether anything holds the loop up. Printed per phase: request count
and latency p50 / p95 / max (ms), and the load average. It asserts
nothing: it is a measurement (the issue's bar: a long upload slows no other request by more than
100 ms).
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.session_fixtures import corridor_session  # noqa: E402

BOUNDARY = "slam6d-slow-upload-boundary"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def scan_block(seed: int = 0, points: int = 40_000) -> bytes:
    """About 1 MB of uos scan text (cm, three numbers a line)."""
    xyz = np.random.default_rng(seed).uniform(-2000.0, 2000.0, (points, 3))
    return "".join(f"{x:.3f} {y:.3f} {z:.3f}\n" for x, y, z in xyz).encode()


def multipart(total_mb: float, rate_mb: float, sent: threading.Event) -> Iterator[bytes]:
    """The upload body (a name field, one ``scan000.3d``), yielded at ``rate_mb`` MB/s in 64 KiB pieces."""
    head = (
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="name"\r\n\r\nSlow upload\r\n'
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="files"; filename="scan000.3d"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    yield head
    block = scan_block()
    repeats = max(1, int(total_mb * 1e6 / len(block)))
    piece = 64 * 1024
    start = time.monotonic()
    sent_bytes = 0
    for _ in range(repeats):
        for offset in range(0, len(block), piece):
            chunk = block[offset : offset + piece]
            sent_bytes += len(chunk)
            ahead = sent_bytes / (rate_mb * 1e6) - (time.monotonic() - start)
            if ahead > 0:
                time.sleep(ahead)
            yield chunk
    yield f"\r\n--{BOUNDARY}--\r\n".encode()
    sent.set()


def body_length(total_mb: float) -> int:
    return sum(len(part) for part in multipart(total_mb, 1e12, threading.Event()))


PAGE = "page requests"
PROBE = "event-loop probe"


def poll(url: str, paths: list[str], stop: threading.Event, phase: list[str], latency: dict[str, list[float]]) -> None:
    with httpx.Client(base_url=url, timeout=120) as client:
        k = 0
        while not stop.is_set():
            now_phase = phase[0]
            start = time.perf_counter()
            client.get(paths[k % len(paths)])
            elapsed = time.perf_counter() - start
            if phase[0] == now_phase:  # a request straddling two phases counts in neither
                latency.setdefault(now_phase, []).append(elapsed)
            k += 1


def load_average() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--upload-mb", type=float, default=200.0)
    parser.add_argument("--rate-mb", type=float, default=20.0, help="upload speed in MB/s")
    parser.add_argument("--seconds", type=float, default=10.0, help="length of the baseline phase")
    parser.add_argument("--pollers", type=int, default=2)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        sessions = Path(tmp) / "sessions"
        corridor_session(sessions, scans=6, points=5000)
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        command = [sys.executable, "-m", "app.main", "--sessions-dir", str(sessions), "--port", str(port)]
        command += ["--max-upload-mb", str(int(args.upload_mb) + 16)]
        server = subprocess.Popen(command, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        try:
            deadline = time.monotonic() + 60
            while True:
                try:
                    if httpx.get(f"{url}/api/sessions/corridor/poses", timeout=5).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                if time.monotonic() > deadline:
                    raise RuntimeError("the workbench did not start")
                time.sleep(0.2)
            print(f"server up; load average {load_average()}")
            phase = ["baseline"]
            latency: dict[str, dict[str, list[float]]] = {PAGE: {}, PROBE: {}}
            stop = threading.Event()
            page = ["/api/sessions/corridor", "/api/sessions/corridor/poses", "/api/sessions"]
            pollers = [
                threading.Thread(target=poll, args=(url, page, stop, phase, latency[PAGE])) for _ in range(args.pollers)
            ]
            # a path no route has: answered 404 on the event loop itself (no worker thread), so its
            # latency shows whether the loop is held up
            probe = threading.Thread(target=poll, args=(url, ["/no-such-page"], stop, phase, latency[PROBE]))
            pollers.append(probe)
            for t in pollers:
                t.start()
            time.sleep(args.seconds)
            sent = threading.Event()
            outcome: list[httpx.Response] = []
            length = body_length(args.upload_mb)

            def upload() -> None:
                headers = {
                    "Content-Type": f"multipart/form-data; boundary={BOUNDARY}",
                    "Content-Length": str(length),
                }
                body = multipart(args.upload_mb, args.rate_mb, sent)
                outcome.append(httpx.post(f"{url}/api/sessions/upload", content=body, headers=headers, timeout=3600))

            phase[0] = "while uploading"
            began = time.monotonic()
            uploader = threading.Thread(target=upload)
            uploader.start()
            sent.wait()
            streamed = time.monotonic() - began
            phase[0] = "while parsing"
            parse_began = time.monotonic()
            uploader.join()
            parsed = time.monotonic() - parse_began
            phase[0] = "after"  # the baseline again: how much the machine's own load drifted meanwhile
            time.sleep(args.seconds)
            phase[0] = "done"
            stop.set()
            for t in pollers:
                t.join()
        finally:
            server.terminate()
            server.wait(30)

    answer = outcome[0]
    print(
        f"\nupload of {length / 1e6:.0f} MB at {args.rate_mb:g} MB/s: streamed in {streamed:.1f} s, answered "
        f"{answer.status_code} {parsed:.1f} s after its last byte; {args.pollers} pollers"
    )
    if answer.status_code >= 400:
        print(f"  {answer.text[:300]}")
    print(f"{'requests':18} {'phase':16} {'count':>6} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8}")
    for kind, phases in latency.items():
        for name in ("baseline", "while uploading", "while parsing", "after"):
            ms = [1000 * v for v in phases.get(name, [])]
            if ms:
                p50, p95 = np.percentile(ms, 50), np.percentile(ms, 95)
                print(f"{kind:18} {name:16} {len(ms):6d} {p50:8.1f} {p95:8.1f} {max(ms):8.1f}")
    print(f"load average after: {load_average()}")


if __name__ == "__main__":
    main()
