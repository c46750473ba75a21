"""Traces of registration runs: recorded while the pipeline runs, replayed later without recomputing.

A trace is every event of a run (:mod:`slam6d.pipeline`) made plain JSON by
:func:`slam6d.trace.to_jsonable`, stored as ``traces/<name>.json`` in the session folder; the
journal entry of the run names it. Replaying turns the events into frames - which scans moved
where, which pair was matched, the RMS so far - so the 3D view can step through a finished run
from the file alone. Two things are trimmed to keep a trace small: the octree search's full
candidate grids (only the guess's result is kept) and the per-iteration list repeated inside each
scan's final ICP result (the iterations are events of their own).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.errors import EditError
from slam6d.events import Event, ScanRegistered, ScanStarted
from slam6d.session import Session
from slam6d.trace import read_trace, to_jsonable, write_trace

TRACE_DIR = "traces"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


def compact_event(event: Event) -> dict[str, Any]:
    """One pipeline event as JSON with its type name; heavy parts replaced by what a replay needs."""
    data: dict[str, Any] = {"type": type(event).__name__}  # the stored name a replay reads back
    if isinstance(event, ScanStarted):
        guess = event.guess
        data.update(
            index=int(event.index),
            initial=to_jsonable(event.initial),
            model_indices=[int(i) for i in event.model_indices],
            guess=None
            if guess is None
            else {"transform": to_jsonable(guess.transform), "score": int(guess.score), "seconds": guess.seconds},
        )
    elif isinstance(event, ScanRegistered):
        result = {k: v for k, v in to_jsonable(event.result).items() if k != "iterations"}
        data.update(index=int(event.index), pose=to_jsonable(event.pose), result=result)
    else:
        data.update(to_jsonable(event))
    return data


class TraceRecorder:
    """Collects a pipeline's events as it steps (both ``run`` and ``step_scan`` go through ``step``)."""

    def __init__(self) -> None:
        self.events: list[dict[str, Any]] = []

    def add(self, event: Event) -> None:
        self.events.append(compact_event(event))

    def attach(self, pipeline: Any) -> Any:
        step = pipeline.step

        def recording_step() -> Any:
            event = step()
            self.add(event)
            return event

        pipeline.step = recording_step
        return pipeline

    def save(self, session: Session, initial_poses: list[Any], meta: dict[str, Any] | None = None) -> str:
        """Write the trace into the session folder; returns its name (for the journal entry)."""
        folder = Path(session.folder) / TRACE_DIR
        folder.mkdir(exist_ok=True)
        name = f"run-{time.strftime('%Y%m%d-%H%M%S')}-{int(time.time() * 1000) % 1000:03d}"
        while (folder / f"{name}.json").exists():
            name += "x"
        trace = {"name": name, "meta": meta or {}, "initial_poses": to_jsonable(initial_poses), "events": self.events}
        write_trace(folder / f"{name}.json", trace)
        return name


def list_traces(session: Session) -> list[dict[str, Any]]:
    folder = Path(session.folder) / TRACE_DIR
    if not folder.is_dir():
        return []
    found = []
    for path in sorted(folder.glob("*.json"), key=lambda p: p.stat().st_mtime):
        found.append({"name": path.stem, "bytes": path.stat().st_size})
    return found


def load_trace(session: Session, name: str) -> dict[str, Any]:
    path = Path(session.folder) / TRACE_DIR / f"{name}.json"
    if not _NAME.match(name) or not path.is_file():
        raise EditError(f"no trace '{name}' in this session", 404)
    return read_trace(path)


@dataclass
class ReplayFrame:
    """What the view shows after one event of a replay."""

    event: int
    kind: str
    moved: dict[int, np.ndarray]  # scan -> world_from_scan set by this event
    current: int | None
    model: list[int]
    rms_history: list[tuple[int, float, int]] = field(default_factory=list)  # (iteration, rms, pairs) of the scan
    text: str = ""


def replay_frames(trace: dict[str, Any]) -> list[ReplayFrame]:
    """The frames of a stored trace, in order; the poses come from the events, nothing is recomputed."""
    frames: list[ReplayFrame] = []
    current: int | None = None
    model: list[int] = []
    history: list[tuple[int, float, int]] = []
    poses = [np.asarray(p, dtype=np.float64) for p in trace.get("initial_poses", [])]
    for n, event in enumerate(trace["events"]):
        kind = event["type"]
        moved: dict[int, np.ndarray] = {}
        text = kind
        if kind == "ScanStarted":
            current, model, history = int(event["index"]), list(event["model_indices"]), []
            moved[current] = np.asarray(event["initial"])
            guessed = " (octree guess)" if event.get("guess") else ""
            text = f"scan {current} starts against {model}{guessed}"
        elif kind == "IcpIterated":
            it = event["iteration"]
            history = [*history, (int(it["index"]), float(it["rms"] or 0.0), int(it["pairs"]))]
            moved[int(event["index"])] = np.asarray(event["pose"])
            text = f"scan {event['index']} · iteration {it['index']} · RMS {it['rms']:.4f} m · {it['pairs']} pairs"
        elif kind == "ScanRegistered":
            moved[int(event["index"])] = np.asarray(event["pose"])
            text = f"scan {event['index']} registered (RMS {event['result']['rms']:.4f} m)"
        elif kind == "LoopsDetected":
            hyps = event["hypotheses"]
            text = f"{len(hyps)} loop hypotheses, {sum(1 for h in hyps if h['accepted'])} accepted"
        elif kind == "LoopClosed":
            text = f"loop {event['loop']['i']}-{event['loop']['j']} closed"
        elif kind == "RelaxationProgressed":
            text = f"relaxation round {event['iteration']}: residual {100 * event['residual']:.2f} cm"
        elif kind == "Finished":
            current, model = None, []
            text = "finished"
        for k, pose in moved.items():
            if k < len(poses):
                poses[k] = pose
        frames.append(ReplayFrame(n, kind, moved, current, model, history, text))
    final = trace.get("meta", {}).get("final_poses")
    if final is not None and frames:  # loop closing and relaxation move many scans at once
        frames[-1].moved = {k: np.asarray(p) for k, p in enumerate(final)}
    return frames
