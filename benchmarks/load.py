"""Load on a shared workbench with tokens on: pollers, 3D-view websockets, edits and a relaxation at once.

    .venv/bin/python benchmarks/load.py [--pollers 20] [--sockets 5] [--listeners 5] [--seconds 60]
        [--scans 12] [--points 20000]

A workbench server runs in this process (uvicorn in a thread, as the browser tests start it) over
the tests' corridor session, with tokens required as when it is bound off loopback. For ``--seconds``:

* ``--pollers`` clients, each with its own viewer token, poll back to back what a session page
  polls (``GET /api/sessions/{id}``) and the poses (``GET .../poses``);
* ``--sockets`` clients hold the 3D view's websocket through the proxy (viewer tokens, the page's
  Origin) and read every message viser sends them;
* ``--listeners`` clients hold a session page's event stream (``/api/sessions/{id}/events``, viewer
  tokens), which tells them of every new head;
* one editor moves a scan every second (alternating scans), and relaxation jobs run back to back.

Printed: requests per kind, latency percentiles (p50, p95, max), error count by status, websocket
messages and bytes received, edits acknowledged / refused (409: a relaxation moved that scan meanwhile), relaxations done /
refused, and "edit -> page told": from sending a move to each listener hearing of its revision. It
asserts nothing: it is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app.tokens import Role  # noqa: E402
from slam6d.session import Session  # noqa: E402
from tests.browser.conftest import LiveServer  # noqa: E402
from tests.session_fixtures import corridor_session  # noqa: E402

SESSION = "load"
# measured too, but not answers to a request: left out of "all requests"
NOT_REQUESTS = frozenset({"open 3D-view socket", "edit -> page told"})


class Recorder:
    """Latencies and outcomes, shared by every client thread."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.latency: dict[str, list[float]] = defaultdict(list)
        self.errors: Counter[str] = Counter()
        self.notes: Counter[str] = Counter()
        self.edit_sent: dict[int, float] = {}  # revision of an acknowledged move -> when it was sent
        self.told: list[dict[int, float]] = []  # per listener: revision -> when the event arrived

    def request(self, kind: str, call: Any) -> httpx.Response | None:
        start = time.perf_counter()
        try:
            response = call()
        except httpx.HTTPError as exc:
            with self.lock:
                self.errors[f"{kind}: {type(exc).__name__}"] += 1
            return None
        elapsed = time.perf_counter() - start
        with self.lock:
            self.latency[kind].append(elapsed)
            if response.status_code >= 400 and response.status_code not in (409, 412):  # refusals are counted apart
                self.errors[f"{kind}: {response.status_code}"] += 1
        return response

    def note(self, what: str) -> None:
        with self.lock:
            self.notes[what] += 1


def poller(url: str, token: str, stop: float, record: Recorder) -> None:
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as client:
        while time.monotonic() < stop:
            record.request("poll session", lambda: client.get(f"/api/sessions/{SESSION}"))
            record.request("poll poses", lambda: client.get(f"/api/sessions/{SESSION}/poses"))


async def socket_reader(ws_url: str, origin: str, token: str, stop: float, record: Recorder) -> None:
    import viser
    from websockets import Subprotocol
    from websockets.asyncio.client import connect

    headers = {"Authorization": f"Bearer {token}", "Origin": origin}
    protocol = Subprotocol(f"viser-v{viser.__version__}")  # what the viser client offers
    opening = time.perf_counter()
    try:
        # a browser waits for the handshake as long as it takes (the proxy admits one arriving browser at
        # a time): so does this client, and the wait is measured
        async with connect(
            ws_url, additional_headers=headers, subprotocols=[protocol], max_size=None, open_timeout=120
        ) as socket:
            record.note("websocket opened")
            with record.lock:
                record.latency["open 3D-view socket"].append(time.perf_counter() - opening)
            while time.monotonic() < stop:
                try:
                    message = await asyncio.wait_for(socket.recv(), timeout=max(0.1, stop - time.monotonic()))
                except TimeoutError:
                    break
                record.note("websocket messages")
                with record.lock:
                    record.notes["websocket bytes"] += len(message)
    except Exception as exc:  # a refused or dropped socket is what this measures
        with record.lock:
            record.errors[f"websocket: {type(exc).__name__}: {str(exc)[:80]}"] += 1


async def event_listener(events_url: str, origin: str, token: str, stop: float, record: Recorder) -> None:
    """A session page's event stream: note when each revision was told."""
    import json

    from websockets.asyncio.client import connect

    told: dict[int, float] = {}
    with record.lock:
        record.told.append(told)
    headers = {"Authorization": f"Bearer {token}", "Origin": origin}
    try:
        async with connect(events_url, additional_headers=headers) as socket:
            record.note("event streams opened")
            while time.monotonic() < stop:
                try:
                    message = await asyncio.wait_for(socket.recv(), timeout=max(0.1, stop - time.monotonic()))
                except TimeoutError:
                    break
                event = json.loads(message)
                record.note(f"events: {event['type']}")
                if event["type"] == "revision":
                    told.setdefault(int(event["revision"]), time.perf_counter())
    except Exception as exc:
        with record.lock:
            record.errors[f"event stream: {type(exc).__name__}: {str(exc)[:80]}"] += 1


def sockets(
    ws_url: str, events_url: str, origin: str, tokens: list[str], listeners: list[str], stop: float, record: Recorder
) -> None:
    async def all_sockets() -> None:
        await asyncio.gather(
            *(socket_reader(ws_url, origin, t, stop, record) for t in tokens),
            *(event_listener(events_url, origin, t, stop, record) for t in listeners),
        )

    asyncio.run(all_sockets())


def editor(url: str, token: str, stop: float, scans: int, record: Recorder) -> None:
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=120) as client:
        n = 0
        while time.monotonic() < stop:
            scan = 1 + n % (scans - 1)
            poses = client.get(f"/api/sessions/{SESSION}/poses").text.split("\n")
            row = np.array([float(v) for v in poses[scan].split()]).reshape(3, 4)
            pose = np.vstack([row, [0, 0, 0, 1]])
            pose[2, 3] += 0.01 if n % 2 == 0 else -0.01
            sent = time.perf_counter()
            moved = record.request(
                "edit (move)",
                partial(client.post, f"/api/sessions/{SESSION}/scans/{scan}/pose", json={"pose": pose.tolist()}),
            )
            if moved is not None and moved.status_code == 200:
                with record.lock:
                    record.edit_sent[int(moved.json()["revision"])] = sent
            if moved is not None:
                record.note(
                    "edits acknowledged" if moved.status_code == 200 else f"edits refused ({moved.status_code})"
                )
            n += 1
            time.sleep(max(0.0, 1.0 - (time.monotonic() % 1.0)))


def relaxer(url: str, token: str, stop: float, record: Recorder) -> None:
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=120) as client:
        while time.monotonic() < stop:
            started = record.request(
                "start relaxation",
                lambda: client.post(f"/api/sessions/{SESSION}/relax", json={"method": "graph", "fixed": [0]}),
            )
            if started is None or started.status_code != 202:
                time.sleep(1.0)
                continue
            job_id = started.json()["id"]
            while True:
                job = client.get(f"/api/jobs/{job_id}").json()
                if job["status"] not in ("queued", "running"):
                    break
                time.sleep(0.2)
            if job["status"] == "done":
                record.note("relaxations done")
            elif "was changed by" in job.get("message", ""):
                record.note("relaxations refused (a scan they move was edited meanwhile)")
            else:
                record.note(f"relaxations {job['status']}: {job.get('message', '')[:80]}")


def corridor_sessions(folder: Path, scans: int, points: int) -> Path:
    """The tests' corridor session (scans along a corridor with 5 cm odometry noise), relaxable over its graph."""
    sessions = folder / "sessions"
    corridor = corridor_session(sessions, scans=scans, points=points, odometry_noise=0.05, engine={"voxel_size": 0.1})
    corridor.rename(sessions / SESSION)
    Session.open(sessions / SESSION).load_sequence()
    return sessions


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pollers", type=int, default=20)
    parser.add_argument("--sockets", type=int, default=5)
    parser.add_argument("--listeners", type=int, default=5, help="event streams (/api/sessions/{id}/events)")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--scans", type=int, default=12)
    parser.add_argument("--points", type=int, default=20000, help="points per corridor scan")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        sessions = corridor_sessions(Path(tmp), args.scans, args.points)
        with LiveServer(sessions, require_token=True) as server:
            tokens = server.app.state.tokens
            viewer_tokens = [tokens.issue(Role.viewer, SESSION, name=f"viewer{n}")[0] for n in range(args.pollers)]
            socket_tokens = [tokens.issue(Role.viewer, SESSION, name=f"view{n}")[0] for n in range(args.sockets)]
            listen_tokens = [tokens.issue(Role.viewer, SESSION, name=f"page{n}")[0] for n in range(args.listeners)]
            editor_token = tokens.issue(Role.editor, SESSION, name="editor")[0]
            warm = httpx.get(
                f"{server.url}/api/sessions/{SESSION}/view", headers={"Authorization": f"Bearer {editor_token}"}
            )
            print(f"view started: {warm.status_code}; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
            record = Recorder()
            stop = time.monotonic() + args.seconds
            ws_url = f"ws://127.0.0.1:{server.port}/viser/{SESSION}"
            threads = [threading.Thread(target=poller, args=(server.url, t, stop, record)) for t in viewer_tokens]
            events_url = f"ws://127.0.0.1:{server.port}/api/sessions/{SESSION}/events"
            threads.append(
                threading.Thread(
                    target=sockets, args=(ws_url, events_url, server.url, socket_tokens, listen_tokens, stop, record)
                )
            )
            threads.append(threading.Thread(target=editor, args=(server.url, editor_token, stop, args.scans, record)))
            threads.append(threading.Thread(target=relaxer, args=(server.url, editor_token, stop, record)))
            started = time.monotonic()
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            wall = time.monotonic() - started

    # from sending an acknowledged move to each listener hearing of the revision it made
    record.latency["edit -> page told"] = [
        told[revision] - sent for told in record.told for revision, sent in record.edit_sent.items() if revision in told
    ]
    print(
        f"\n{args.pollers} pollers, {args.sockets} websockets, {args.listeners} event streams, 1 editor, "
        "relaxations back to back; "
        f"{wall:.0f} s; corridor of {args.scans} scans x {args.points} points; tokens required"
    )
    print(f"{'request':20} {'count':>7} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8}")
    for kind, values in sorted(record.latency.items()):
        ms = [1000 * v for v in values]
        print(f"{kind:20} {len(ms):7d} {percentile(ms, 50):8.0f} {percentile(ms, 95):8.0f} {max(ms):8.0f}")
    every = [1000 * v for kind, values in record.latency.items() if kind not in NOT_REQUESTS for v in values]
    print(
        f"{'all requests':20} {len(every):7d} {percentile(every, 50):8.0f} {percentile(every, 95):8.0f} {max(every):8.0f}"
    )
    print(f"errors: {sum(record.errors.values())}" + "".join(f"\n  {k}: {v}" for k, v in sorted(record.errors.items())))
    for what, count in sorted(record.notes.items()):
        print(f"{what}: {count}")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
