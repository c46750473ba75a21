"""Viewer benchmark: time to the first full map of a large session in headless Chromium, and the
rate of pose-only updates (what ICP stepping sends).

Targets: 77 scans x 100k points on screen within 3 s of opening the page (the scans are read and
cached before timing, as a reopened session is); stepping updates at >= 20 per second.

    .venv/bin/python benchmarks/viewer.py [--scans 77] [--points 100000]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from slam6d.geometry import pose_from_xyzrpy  # noqa: E402
from slam6d.session import Session  # noqa: E402
from tests.browser.conftest import CHROMIUM_ARGS, LiveServer, map_pixels  # noqa: E402
from tests.session_fixtures import write_corridor_scans  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=77)
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--updates", type=int, default=100)
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "sessions"
        t0 = time.perf_counter()
        write_corridor_scans(root / "big" / "scans", scans=args.scans, points=args.points)
        session = Session.create(root / "big", "Benchmark", "scans")
        session.load_sequence()  # parse once and fill the cache, as a session opened before
        print(f"simulated and cached {args.scans} x {args.points} points in {time.perf_counter() - t0:.1f} s")

        with LiveServer(root) as server, sync_playwright() as playwright:
            context = playwright.chromium.launch_persistent_context(
                str(Path(tmp) / "profile"),
                executable_path="/usr/bin/chromium",
                args=CHROMIUM_ARGS,
                headless=True,
                viewport={"width": 1280, "height": 800},
            )
            page = context.pages[0] if context.pages else context.new_page()
            start = time.perf_counter()
            page.goto(f"{server.url}/sessions/big")
            page.frame_locator("#viewer").get_by_text("points shown").wait_for(timeout=300_000)
            while map_pixels(page) < 0.05 and time.perf_counter() - start < 120:
                time.sleep(0.05)
            first_map = time.perf_counter() - start
            viewer = server.app.state.viewers.get("big")
            shown = viewer.as_dict()["points_shown"]
            print(f"first full map: {first_map:.2f} s ({shown:,} points shown of {args.scans * args.points:,})")

            # pose-only updates, as ICP stepping sends them: one scan node moves per update
            base = viewer.poses[args.scans // 2].copy()
            start = time.perf_counter()
            for k in range(args.updates):
                pose = base @ pose_from_xyzrpy(0.01 * np.sin(k / 5), 0, 0, 0, 0, 0.002 * k)
                poses = [np.eye(4)] * args.scans
                poses[args.scans // 2] = pose
                viewer.set_poses(poses, [args.scans // 2])
                page.frame_locator("#viewer").locator("canvas").first.evaluate(
                    "c => new Promise(r => requestAnimationFrame(() => r(c.width)))"
                )
            rate = args.updates / (time.perf_counter() - start)
            print(f"pose-only updates: {rate:.1f} per second (each followed by a browser frame)")
            context.close()
        verdict = "OK" if first_map <= 3.0 and rate >= 20 else "BELOW TARGET"
        print(f"targets: first map <= 3 s, updates >= 20/s -> {verdict}")


if __name__ == "__main__":
    main()
