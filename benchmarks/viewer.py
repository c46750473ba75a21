"""Viewer benchmark: time to the first full map of a large session in headless Chromium, and the
rate at which pose-only updates (what ICP stepping sends) reach the browser and are drawn.

Targets: 77 scans x 100k points (every scan) on screen within 3 s of opening the page; stepping
updates at >= 20 per second.

    .venv/bin/python benchmarks/viewer.py [--scans 77] [--shots 149000] [--rate 30] [--seconds 5]
    .venv/bin/python benchmarks/viewer.py --world campus --scans 1000 --shots 200000 --seed 3   # 100M points
    .venv/bin/python benchmarks/viewer.py --scans-dir campus --first-view   # the first view step by step, memory after the edge colours

The session comes from ``slam6d.simulate`` (``--shots`` laser shots per scan: about two thirds return
in the loop world and one half in the campus, so 149,000 shots give ~100k points per scan there and
200,000 here), or from ``--scans-dir`` (scans written before, e.g. by ``slam6d simulate``). The scans,
a session over them opened once (parsed cache, revision 0, levels of detail: the one-time work of a
first open, timed and printed when done) are kept in ``--cache`` (default: a folder under the system
temp dir) between runs; each run opens a fresh session folder with that journal and cache, as a
session reopened on the workbench is. The viewer itself starts on the request for the page, so its
work (reading the levels, choosing them, sending) is inside the timed span. The workbench server runs
in this process, so the resident memory printed is the server's (the first open's work is done in a
child process and does not count).

What is measured, in the browser (a script injected into the viewer's frame before it loads):

* every batch of messages the viser client hands from its websocket worker to the page, with the
  number of point clouds and of pose updates of the moving scan it carries;
* every frame the 3D view renders, with the number of points its draw calls covered. Each such
  frame ends with a one-pixel ``readPixels``, which waits until the (software) renderer has
  really drawn it, so its timestamp is when the frame exists, not when its commands were queued.
  The canvas keeps its drawing buffer (viser sets ``preserveDrawingBuffer``), so this reads the
  frame just drawn.

The viewer sends the map in two passes (the first look: every scan in one cloud within the first-look
budget, then every scan at the full budget).
Whole map first drawn = from ``page.goto`` (which returns as soon as the response starts, so every
step is seen from the navigation's start) until the end of the first frame that drew every point
of the first look; its steps are printed too: the viewer started (the page request starts it), the
first look sent, the viser client page started in its frame, its first message and the first look
arrived there. Full budget drawn = until the first frame that drew every point of the full pass.
``--first-view`` stops after the first look is drawn and instead waits until the graph's edges are
coloured by residual, then prints the server's memory (what that colouring reads stays bounded). A single-pass view (a budget at or under the coarse one) gives
the same time for both. A screenshot afterwards checks the canvas shows the map.
Pose updates: a thread moves one scan at ``--rate`` per second for ``--seconds`` through
``SessionViewer.set_poses`` (what the stepper calls), between ``begin_playback`` with that scan and
its predecessor as the current pair and ``end_playback``, as the stepper's Play and Pause do
(``--no-playback`` streams over the whole map at the full budget instead, as single steps are shown);
reported are the updates that arrived in the page per second, and the frames per second that drew
a newly arrived pose (updates arriving while a frame renders are drawn together by the next one:
the viewer shows the latest pose).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from slam6d.geometry import pose_from_xyzrpy  # noqa: E402
from slam6d.scan_levels import LEVELS_DIR, ScanLevels, session_levels  # noqa: E402
from slam6d.session import CACHE_DIR, JOURNAL_FILE, Session  # noqa: E402
from slam6d.simulate import SimulationConfig, simulate_session  # noqa: E402
from tests.browser.conftest import CHROMIUM_ARGS, LiveServer, map_pixels  # noqa: E402

SESSION_ID = "big"

# Runs in every frame before its scripts; only the viser client page records anything.
INSTRUMENT = r"""
(() => {
  if (!location.pathname.startsWith("/viser/")) return;
  const bench = { frames: [], batches: [], poseName: null, pageStart: performance.timeOrigin, longTasks: [] };
  window.__bench = bench;
  // main-thread tasks over 50 ms (script compile and run, frames): [start, duration] in ms of this page
  new PerformanceObserver((list) => {
    for (const task of list.getEntries()) bench.longTasks.push([task.startTime, task.duration]);
  }).observe({ type: "longtask", buffered: true });
  let points = 0, gl = null, posesSinceFrame = 0;
  const pixel = new Uint8Array(4);
  for (const proto of [WebGLRenderingContext.prototype, WebGL2RenderingContext.prototype]) {
    const draw = proto.drawArrays;
    proto.drawArrays = function (mode, first, count) {
      if (mode === 0) { points += count; gl = this; }  // gl.POINTS
      return draw.call(this, mode, first, count);
    };
  }
  const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (callback) => raf((time) => {
    points = 0;
    const poses = posesSinceFrame;
    posesSinceFrame = 0;
    const t0 = performance.now();
    callback(time);
    if (points > 0) {
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);  // waits until the frame is drawn
      bench.frames.push([Date.now(), points, poses, performance.now() - t0]);
    } else {
      posesSinceFrame += poses;  // nothing drawn: those poses are still to be shown
    }
  });
  const NativeWorker = window.Worker;
  window.Worker = class extends NativeWorker {
    constructor(...args) {
      super(...args);
      this.addEventListener("message", (event) => {
        const data = event.data;
        if (!data || data.type !== "message_batch") return;
        let clouds = 0, poses = 0;
        for (const m of data.messages) {
          if (m.type === "PointCloudMessage") clouds += 1;
          else if (m.type === "SetPositionMessage" && m.name === bench.poseName) poses += 1;
        }
        posesSinceFrame += poses;
        bench.batches.push([Date.now(), clouds, poses, data.messages.length]);
      });
    }
  };
})();
"""


def load_average() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def process_cpu(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far, all its threads included."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def process_kind(pid: int) -> str:
    """What a child process is: Chromium's ``--type`` (renderer, gpu-process, utility, zygote; ``webui``
    for the renderer of the browser's own pages), ``browser`` for Chromium's own process, ``driver`` for
    Playwright's, else its command name. (A process forked from Chromium's zygote has its command line
    as one string.)"""
    line = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    kind = re.search(r"--type=(\S+)", line)
    if kind:
        return "webui" if "--top-chrome-webui" in line else kind.group(1)
    name = Path(f"/proc/{pid}/comm").read_text().strip()
    return "browser" if "chrom" in name else "driver" if name.startswith("node") else name


def cpu_by_process() -> dict[str, float]:
    """CPU seconds used so far by the workbench server (this process less its main thread, which runs the
    benchmark's polling), the benchmark itself, and each kind of process under it (Playwright's driver,
    Chromium's browser, renderer, GPU process...): the CPU a step costs, whatever else the machine runs."""
    cpu = {"server": time.process_time() - time.thread_time(), "benchmark": time.thread_time()}
    children = [os.getpid()]
    while children:
        pid = children.pop()
        try:  # (a child is listed under the thread that started it: Chromium starts them off its main thread)
            kids = [
                int(k) for task in Path(f"/proc/{pid}/task").iterdir() for k in (task / "children").read_text().split()
            ]
            for kid in kids:
                kind = process_kind(kid)
                cpu[kind] = cpu.get(kind, 0.0) + process_cpu(kid)
            children += kids
        except (OSError, ValueError):
            continue  # it ended meanwhile
    return cpu


def cpu_spent(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
    return {k: after[k] - before.get(k, 0.0) for k in after}


def settle_browser(limit_s: float = 20.0) -> float:
    """Wait until the just-started browser is idle (< 5 % of a core over half a second): a new headless
    Chromium spends its first second or two on its own pages, which is not the workbench's first view
    (a person opens a session in a browser already running). Returns the seconds waited."""
    start = time.perf_counter()
    before = sum(v for k, v in cpu_by_process().items() if k not in ("server", "benchmark"))
    while time.perf_counter() - start < limit_s:
        time.sleep(0.5)
        now = sum(v for k, v in cpu_by_process().items() if k not in ("server", "benchmark"))
        if now - before < 0.025:
            break
        before = now
    return time.perf_counter() - start


def simulated_scans(cache: Path, scans: int, shots: int, seed: int, world: str, scans_dir: Path | None) -> Path:
    """A session over the scans, opened once so its parsed cache, journal and levels of detail exist;
    made once per set of scans (in a child process, so this one never holds the scans: its memory
    is the workbench's). Returns the session folder."""
    name = scans_dir.resolve().name if scans_dir else f"{world}-{scans}x{shots}-seed{seed}"
    folder = cache / name
    parsed = folder / "parsed" / "session"
    if not (parsed / CACHE_DIR / LEVELS_DIR).is_dir():
        t0 = time.perf_counter()
        if folder.exists():
            shutil.rmtree(folder)
        source = scans_dir.resolve() if scans_dir else folder / "scans"
        if scans_dir is None:
            config = SimulationConfig(scans=scans, points_per_scan=shots, seed=seed, world=world)
            simulate_session(source, config)
        Session.create(parsed, "parse", source)
        child = multiprocessing.get_context("spawn").Process(target=open_once, args=(parsed,))
        child.start()
        child.join()
        if child.exitcode != 0:
            raise SystemExit(f"preparing {parsed} failed")
        print(f"prepared {source} (parsed, levels of detail) in {time.perf_counter() - t0:.1f} s into {folder}")
    return parsed


def open_once(folder: Path) -> None:
    """What the first open of a session does once: parse the scans, store revision 0, order the levels."""
    session = Session.open(folder)
    t0 = time.perf_counter()
    sequence = session.load_sequence()
    t1 = time.perf_counter()
    session_levels(session, lambda: sequence.scans)
    print(f"parsed {len(sequence)} scans in {t1 - t0:.1f} s, levels of detail in {time.perf_counter() - t1:.1f} s")


def reopened_session(parsed: Path, folder: Path, engine: dict[str, Any]) -> None:
    """A new session folder over the same scans with the prepared journal and caches (hard links)."""
    config = Session.open(parsed).config
    Session.create(folder, "Benchmark", config.sources, config.format_name, config.frame, engine=engine)
    shutil.copy(parsed / JOURNAL_FILE, folder / JOURNAL_FILE)
    shutil.copytree(parsed / CACHE_DIR, folder / CACHE_DIR, copy_function=os.link)


def memory_mb() -> tuple[float, float]:
    """This process's resident memory now and at its peak (MB): the workbench server runs in it."""
    fields = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":" in line)
    return int(fields["VmRSS"].split()[0]) / 1024, int(fields["VmHWM"].split()[0]) / 1024


def stream_poses(viewer: Any, index: int, rate: float, seconds: float) -> tuple[int, float]:
    """Move one scan as the stepper does; returns (updates sent, mean server-side cost per update in s)."""
    base = viewer.scans.poses[index].copy()
    assert viewer.scans.focus is None or index in viewer.scans.focus
    count, busy = 0, 0.0
    start = time.perf_counter()
    while (now := time.perf_counter()) - start < seconds:
        pose = base @ pose_from_xyzrpy(0.05 * np.sin(count / 5), 0, 0, 0, 0, 0.01 * np.sin(count / 7))
        poses = [np.eye(4)] * (index + 1)
        poses[index] = pose
        viewer.set_poses(poses, [index])
        busy += time.perf_counter() - now
        count += 1
        time.sleep(max(0.0, start + count / rate - time.perf_counter()))
    viewer.set_poses([*[np.eye(4)] * index, base], [index])
    return count, busy / max(count, 1)


def first_full_map(page: Any, server: LiveServer, url: str, first_only: bool = False) -> dict[str, Any]:
    """Open the page; seconds from ``goto`` to each step of the first view (see :func:`print_first_view`).

    ``goto`` returns once the response starts (not at the page's load event, which waits for the
    viser client in its frame): the steps are polled from then on. ``first_only`` stops at the
    first frame that drew the whole map (the coarse pass), without waiting for the full budget.
    The page records when each frame was drawn, so polling only learns of it: each poll fetches the
    frames not seen yet (a few numbers), which keeps the benchmark's own CPU use small.
    """
    cpu_before = cpu_by_process()
    start = time.time()
    page.goto(url, wait_until="commit")
    marks: dict[str, Any] = {}
    frame, coarse, shown = None, 0, 0
    frames: list[list[float]] = []
    while "full_map" not in marks:
        if time.time() - start > 600:
            raise SystemExit(f"no full map within 10 minutes (so far: {marks})")
        viewer = server.app.state.viewers.existing(SESSION_ID)
        if viewer is not None:
            marks.setdefault("viewer_started", time.time() - start)
            coarse = coarse or viewer.stream.coarse_points
            if coarse and "coarse_sent" not in marks:
                marks["coarse_sent"] = time.time() - start
            if "viewer_ready" not in marks and viewer.ready.is_set():
                marks["viewer_ready"] = time.time() - start
                if viewer.error:
                    raise SystemExit(f"viewer failed: {viewer.error}")
                shown = viewer.as_dict()["points_shown"]
                coarse = coarse or shown  # one pass: the first map is the full one
        frame = frame or page.frame(url=re.compile(r"/viser/"))
        if frame is not None and coarse:
            frames += frame.evaluate(f"window.__bench ? window.__bench.frames.slice({len(frames)}) : []")
            whole = [f for f in frames if f[1] >= coarse]
            if whole and "whole_map" not in marks:
                marks["whole_map"] = whole[0][0] / 1000.0 - start
                marks["whole_frame_ms"] = whole[0][3]
                marks["cpu"] = cpu_spent(cpu_before, cpu_by_process())
                if first_only:
                    break
            full = [f for f in frames if shown and f[1] >= shown]
            if full:
                marks["full_map"] = full[0][0] / 1000.0 - start
                marks["frame_ms"] = full[0][3]
        page.wait_for_timeout(20)  # (not time.sleep: the sync API learns of the viser frame only while called)
    assert frame is not None
    bench = frame.evaluate("window.__bench")
    marks["client_page"] = bench["pageStart"] / 1000.0 - start
    marks["first_message"] = bench["batches"][0][0] / 1000.0 - start
    clouds = [b for b in bench["batches"] if b[1]]
    marks["first_scans"] = clouds[0][0] / 1000.0 - start
    marks["last_scan"] = clouds[-1][0] / 1000.0 - start
    # the viser client page's own timeline (ms from its start): its file, parsed; long tasks until the map
    timing = frame.evaluate("performance.getEntriesByType('navigation')[0].toJSON()")
    marks["client_loaded_ms"] = timing["responseEnd"]
    marks["client_parsed_ms"] = timing["domContentLoadedEventEnd"]
    marks["client_bytes"] = timing["transferSize"]
    drawn_ms = 1000.0 * (marks["whole_map"] - marks["client_page"])
    marks["long_tasks"] = [t for t in bench["longTasks"] if t[0] < drawn_ms]
    marks["points_coarse"], marks["points_shown"] = coarse, shown
    marks["frame"], marks["viewer"] = frame, viewer
    return marks


def print_first_view(first: dict[str, Any], total: int, load: str) -> None:
    """The first view's timeline, each step in seconds after ``page.goto``, and the CPU each process spent."""
    print(
        f"whole map first drawn (coarse): {first['whole_map']:.2f} s, {first['points_coarse']:,} points; steps: "
        f"viewer started {first['viewer_started']:.2f} s, first look sent {first.get('coarse_sent', float('nan')):.2f} s, "
        f"viser client page started {first['client_page']:.2f} s, its first message {first['first_message']:.2f} s, "
        f"first look in the page {first['first_scans']:.2f} s, drawn {first['whole_map']:.2f} s (that frame "
        f"{first['whole_frame_ms']:.0f} ms); {total:,} points in the session; load {load}"
    )
    tasks = first["long_tasks"]
    print(
        f"viser client page: {first['client_bytes'] / 1e3:,.0f} kB loaded in {first['client_loaded_ms']:.0f} ms, parsed at "
        f"{first['client_parsed_ms']:.0f} ms; {len(tasks)} long tasks until the map was drawn, "
        f"{sum(t[1] for t in tasks) / 1000:.2f} s of its {first['whole_map'] - first['client_page']:.2f} s "
        f"(longest {max((t[1] for t in tasks), default=0):.0f} ms)"
    )
    print(
        cpu_line(f"CPU from page.goto to the map drawn: {{total}} in all over {first['whole_map']:.2f} s", first["cpu"])
    )


def cpu_line(heading: str, cpu: dict[str, float]) -> str:
    """``heading`` (its ``{total}`` filled in) and each process's CPU seconds, the largest first."""
    total = f"{sum(cpu.values()):.2f} s"
    parts = (f"{k} {v:.2f} s" for k, v in sorted(cpu.items(), key=lambda kv: -kv[1]) if v >= 0.005)
    return heading.format(total=total) + " - " + ", ".join(parts)


def open_again(page: Any, server: LiveServer) -> None:
    """The session opened again in the same browser (its view running, its full pass shown): what the
    browser keeps between opens (the 3D client's files, their compiled code) shortens the client's
    start-up, from its page starting to its first message."""
    page.goto("about:blank")
    settle_browser()
    load = load_average()
    again = first_full_map(page, server, f"{server.url}/sessions/{SESSION_ID}", True)
    print(
        f"opened again: viser client page started {again['client_page']:.2f} s, its first message "
        f"{again['first_message']:.2f} s (client start-up {again['first_message'] - again['client_page']:.2f} s; "
        f"{again['client_bytes'] / 1e3:,.0f} kB over the network for its page), map drawn {again['whole_map']:.2f} s "
        f"({again['points_shown'] or again['points_coarse']:,}+ points, that frame {again['whole_frame_ms']:.0f} ms); load {load}"
    )
    print(cpu_line("CPU opening it again: {total} in all", again["cpu"]))


def wait_for_edge_colours(viewer: Any, timeout: float = 1800.0) -> float:
    """Seconds until the graph's edges are coloured by residual for the shown poses (the colouring's reads done)."""
    start = time.perf_counter()
    graph = viewer.graph
    while graph.edge_residual_version != viewer.scans.pose_version:
        if time.perf_counter() - start > timeout:
            raise SystemExit(f"edge residuals not computed within {timeout:.0f} s")
        time.sleep(0.1)
    return time.perf_counter() - start


def pose_update_rates(frame: Any, viewer: Any, rate: float, seconds: float, playback: bool) -> dict[str, Any]:
    """Stream poses of one scan; what arrived in the page and what was drawn, per second."""
    index = len(viewer.scans.nodes) // 2
    frame.evaluate(f"window.__bench.poseName = {viewer.scans.nodes[index].name!r}")
    if playback:
        viewer.begin_playback([index, index - 1])
    time.sleep(1.5)  # let the view settle
    frame.evaluate("window.__bench.frames = []; window.__bench.batches = []")
    sent, cost = stream_poses(viewer, index, rate, seconds)
    time.sleep(1.0)
    bench = frame.evaluate("window.__bench")
    points = [f[1] for f in bench["frames"]]
    if playback:
        viewer.end_playback()
    arrived = sum(b[2] for b in bench["batches"])
    drawn = [f for f in bench["frames"] if f[2]]
    frame_ms = [f[3] for f in bench["frames"]]
    return {
        "sent_per_s": sent / seconds,
        "server_ms": 1000 * cost,
        "arrived": arrived,
        "sent": sent,
        "arrived_per_s": arrived / seconds,
        "drawn_per_s": len(drawn) / seconds,
        "frame_ms": float(np.median(frame_ms)) if frame_ms else float("nan"),
        "frame_points": int(np.median(points)) if points else 0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=77)
    parser.add_argument("--shots", type=int, default=149_000, help="laser shots per scan (~2/3 return)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--world", default="loop", help="simulated world (slam6d simulate --world)")
    parser.add_argument(
        "--scans-dir",
        type=Path,
        default=None,
        help="scans written before (e.g. by slam6d simulate) instead of simulating",
    )
    parser.add_argument("--budget", type=int, default=None, help="display point budget (default: the viewer's)")
    parser.add_argument("--rate", type=float, default=30.0, help="pose updates sent per second")
    parser.add_argument("--seconds", type=float, default=5.0, help="how long poses are streamed")
    parser.add_argument(
        "--no-playback", dest="playback", action="store_false", help="stream poses over the full map, not in Play mode"
    )
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "slam6d-viewer-benchmark")
    parser.add_argument(
        "--first-view",
        action="store_true",
        help="stop at the first view (no full budget, no pose updates); wait for the edge colouring and report memory",
    )
    parser.add_argument(
        "--no-settle",
        dest="settle",
        action="store_false",
        help="open the page at once, while the new browser still starts up (as measured before)",
    )
    parser.add_argument(
        "--again",
        action="store_true",
        help="with --first-view: then open the session again in the same browser (what it keeps between opens)",
    )
    parser.add_argument("--screenshot", type=Path, default=None, help="save the first full map as PNG")
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    parsed = simulated_scans(args.cache, args.scans, args.shots, args.seed, args.world, args.scans_dir)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "sessions"
        engine = {} if args.budget is None else {"display_budget": args.budget}
        reopened_session(parsed, root / SESSION_ID, engine)
        levels = ScanLevels.open(
            root / SESSION_ID / CACHE_DIR / LEVELS_DIR, Session.open(parsed).scan_cache().fingerprint()
        )
        assert levels is not None, "the prepared levels of detail do not match the scans"
        total, count = levels.total_points, len(levels)
        del levels
        print(f"session: {count} scans, {total:,} points")

        with LiveServer(root) as server, sync_playwright() as playwright:
            context = playwright.chromium.launch_persistent_context(
                str(Path(tmp) / "profile"),
                executable_path="/usr/bin/chromium",
                args=CHROMIUM_ARGS,
                headless=True,
                viewport={"width": 1280, "height": 800},
            )
            context.add_init_script(INSTRUMENT)
            context.set_default_timeout(120_000)  # screenshots wait for a frame, which can take seconds
            page = context.pages[0] if context.pages else context.new_page()
            if args.settle:
                print(f"browser idle {settle_browser():.1f} s after it started")
            load = load_average()
            first = first_full_map(page, server, f"{server.url}/sessions/{SESSION_ID}", args.first_view)
            print_first_view(first, total, load)
            rss, peak = memory_mb()
            print(f"server process memory at the first view: {rss:,.0f} MB resident (peak {peak:,.0f} MB)")
            if args.first_view:
                seconds = wait_for_edge_colours(first["viewer"])
                rss, peak = memory_mb()
                print(
                    f"edges coloured by residual {seconds:.1f} s later; server memory then: {rss:,.0f} MB resident "
                    f"(peak {peak:,.0f} MB; load {load_average()})"
                )
                print(f"target: whole map drawn <= 3 s: {'met' if first['whole_map'] <= 3.0 else 'NOT met'}")
                if args.again:
                    open_again(page, server)
                context.close()
                return
            print(
                f"full budget drawn: {first['full_map']:.2f} s, {first['points_shown']:,} of {total:,} points "
                f"(viewer ready {first['viewer_ready']:.2f} s; full-budget scans in the page {first['last_scan']:.2f} s; "
                f"that frame took {first['frame_ms']:.0f} ms to draw; session reopened: parsed scans and levels of "
                f"detail cached; load {load_average()})"
            )
            rss, peak = memory_mb()
            print(f"server process memory after the full budget: {rss:,.0f} MB resident (peak {peak:,.0f} MB)")
            print(f"canvas covered by the map: {map_pixels(page):.0%}")
            if args.screenshot:
                page.screenshot(path=str(args.screenshot))
            load = load_average()
            poses = pose_update_rates(first["frame"], first["viewer"], args.rate, args.seconds, args.playback)
            print(
                f"pose updates: {poses['sent_per_s']:.1f}/s sent ({poses['server_ms']:.2f} ms each on the server), "
                f"{poses['arrived_per_s']:.1f}/s arrived in the page ({poses['arrived']} of {poses['sent']}), "
                f"{poses['drawn_per_s']:.1f} frames/s drew a new pose (median frame {poses['frame_ms']:.0f} ms, "
                f"{poses['frame_points']:,} points; {'playing' if args.playback else 'full map'}; load {load})"
            )
            rss, peak = memory_mb()
            print(f"server process memory at the end: {rss:,.0f} MB resident (peak {peak:,.0f} MB)")
            context.close()
        ok_map, ok_rate = first["whole_map"] <= 3.0, poses["arrived_per_s"] >= 20
        print(
            f"targets: whole map (every scan, coarse) drawn <= 3 s: {'met' if ok_map else 'NOT met'}; "
            f"full budget drawn <= 3 s: {'met' if first['full_map'] <= 3.0 else 'NOT met'}; pose updates >= 20/s reaching "
            f"the page: {'met' if ok_rate else 'NOT met'}, drawn: {'met' if poses['drawn_per_s'] >= 20 else 'NOT met'}"
        )


if __name__ == "__main__":
    main()
