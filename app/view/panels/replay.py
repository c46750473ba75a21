"""Replay of a finished run from its stored trace: the poses come from the file, nothing is recomputed."""

from __future__ import annotations

import threading
import time

import numpy as np

from app import traces
from app.view import display
from app.view.controls import NO_CHOICE
from app.view.panels.host import ViewerHost


class ReplayPanel:
    def __init__(self, viewer: ViewerHost) -> None:
        self.viewer = viewer
        self.session = viewer.state.session
        self.frames: list[traces.ReplayFrame] = []
        self.position = 0
        self._playing = threading.Event()
        self._lock = threading.Lock()
        gui = viewer.server.gui
        with gui.add_folder("Replay a run", expand_by_default=False):
            self.trace = gui.add_dropdown("Trace", [NO_CHOICE])
            self.load = gui.add_button("Load trace")
            self.step = gui.add_button("Next event", disabled=True)
            self.play = gui.add_button("Play replay", disabled=True)
            self.pause = gui.add_button("Pause replay", disabled=True)
            self.stop = gui.add_button("Back to current revision", disabled=True)
            self.status = gui.add_markdown("")
        run = viewer.run_safely
        self.load.on_click(lambda _: run(self._load))
        self.step.on_click(lambda _: run(self._next))
        self.play.on_click(lambda _: run(self._play))
        self.pause.on_click(lambda _: self._playing.clear())
        self.stop.on_click(lambda _: run(self._stop))

    def refresh(self) -> None:
        names = [t["name"] for t in traces.list_traces(self.session)] or [NO_CHOICE]
        previous = self.trace.value
        self.trace.options = names
        self.trace.value = previous if previous in names else names[-1]  # type: ignore[misc]

    def _load(self) -> None:
        if self.trace.value == NO_CHOICE:
            raise ValueError("no stored run yet: run a registration first")
        trace = traces.load_trace(self.session, self.trace.value)
        with self._lock:
            self.frames = traces.replay_frames(trace)
            self.position = 0
        initial = [np.asarray(p) for p in trace["initial_poses"]]
        self.viewer.set_poses(initial)
        self.step.disabled = self.play.disabled = self.stop.disabled = False
        self.status.content = f"{len(self.frames)} events loaded; poses at the run's start"

    def _next(self) -> bool:
        with self._lock:
            if self.position >= len(self.frames):
                self.status.content = f"end of the run ({len(self.frames)} events)"
                return False
            frame = self.frames[self.position]
            self.position += 1
        viewer = self.viewer
        for k, pose in frame.moved.items():
            viewer.set_poses([pose] * (k + 1), [k])
        viewer.colouring.set_highlight(display.pair_colours(frame.current, frame.model))
        if frame.rms_history:
            viewer.controls.show_icp_history(frame.rms_history)
        self.status.content = f"event {frame.event + 1}/{len(self.frames)}: {frame.text}"
        return True

    def _play(self, rate: float = 20.0) -> None:
        if self._playing.is_set():
            return
        self._playing.set()
        self.pause.disabled = False

        def loop() -> None:
            try:
                while self._playing.is_set() and self._next():
                    time.sleep(1.0 / rate)
            finally:
                self._playing.clear()
                self.pause.disabled = True

        threading.Thread(target=loop, name="replay", daemon=True).start()

    def _stop(self) -> None:
        self._playing.clear()
        self.viewer.colouring.highlight = {}
        self.viewer.on_revision()
        self.viewer.colouring.recolour()
        self.status.content = "showing the current revision"
