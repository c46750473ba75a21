"""Registration stepped in the 3D view: one ICP iteration (or one scan) at a time, drawn as it goes."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from app.registration import RunCommit, working_copy
from app.traces import TraceRecorder
from app.view import display
from app.view.panels.host import ViewerHost
from slam6d.engine_settings import pipeline_config
from slam6d.errors import Slam6dError
from slam6d.events import (
    Event,
    Finished,
    IcpIterated,
    LoopClosed,
    LoopsDetected,
    RelaxationProgressed,
    ScanRegistered,
    ScanSkipped,
    ScanStarted,
)
from slam6d.geometry import Matrix
from slam6d.icp import correspondences
from slam6d.pipeline import Pipeline
from slam6d.session_relaxation import registration_readings

MAX_CORRESPONDENCES = 300  # point pairs drawn per ICP iteration


class Stepper:
    """Registration one ICP iteration (or one scan) at a time, drawn as it goes.

    Poses shown while stepping are the pipeline's working estimate; the journal gets a new
    revision only when the run finishes.
    """

    def __init__(self, viewer: ViewerHost, author: str) -> None:
        self.viewer = viewer
        self.author = author
        config = pipeline_config(viewer.state.session.config.engine)
        sequence = working_copy(viewer.state.sequence())
        readings = registration_readings(viewer.state.session, config, [s.has_pose for s in sequence.scans])
        self.pipeline = Pipeline(sequence, config, readings=readings)
        self.recorder = TraceRecorder()  # the stepped run is stored for replay too
        self.recorder.attach(self.pipeline)
        self.run = RunCommit(
            viewer.workbench, viewer.session_id, author, self.pipeline, self.recorder, {"stepped": True}
        )
        self.history: list[tuple[int, float, int]] = []
        self.current: int | None = None
        self.model: list[int] = []
        self.events = 0
        self.finished = False
        self._playing = threading.Event()
        self._lock = threading.Lock()

    def as_dict(self) -> dict[str, Any]:
        return {
            "current": self.current,
            "model": self.model,
            "events": self.events,
            "iterations": len(self.history),
            "rms": [h[1] for h in self.history],
            "playing": self._playing.is_set(),
            "finished": self.finished,
        }

    def step(self) -> None:
        with self._lock:
            if not self.finished:
                self._show_all(self._advance(lambda: [self.pipeline.step()]))

    def next_scan(self) -> None:
        with self._lock:
            if not self.finished:
                self._show_all(self._advance(self.pipeline.step_scan))

    def _advance(self, advance: Callable[[], list[Any]]) -> list[Any]:
        """The next events; when a stage fails, its poses so far are kept as a revision and the
        failure, naming that revision, is raised for the view to show."""
        try:
            return advance()
        except Slam6dError as exc:
            partial = self.run.partial_error(exc)
            if partial is None:
                raise
            self.finished = True
            self.viewer.controls.step_status.content = str(partial.result["kept"])
            raise partial from exc

    def _show_all(self, events: list[Any]) -> None:
        """Draw under the view's lock: a view stopped meanwhile (its server gone) draws nothing."""
        with self.viewer.lock:
            if not self.viewer.stopped:
                for event in events:
                    self._show(event)

    def play(self, rate: float = 30.0) -> None:
        if self._playing.is_set():
            return
        self._playing.set()
        self.viewer.controls.play_button.disabled = True
        self.viewer.controls.pause_button.disabled = False
        self.viewer.begin_playback(self._focus())

        def loop() -> None:
            try:
                while self._playing.is_set() and not self.finished:
                    start = time.monotonic()
                    self.step()
                    time.sleep(max(0.0, 1.0 / rate - (time.monotonic() - start)))
            except Exception as exc:
                self.viewer.warn(f"stepping stopped: {exc}")
            finally:
                self.pause()

        threading.Thread(target=loop, name="stepper", daemon=True).start()

    def pause(self) -> None:
        was_playing = self._playing.is_set()
        self._playing.clear()
        if self.viewer.stopped:
            return
        self.viewer.controls.play_button.disabled = False
        self.viewer.controls.pause_button.disabled = True
        if was_playing:
            self.viewer.end_playback()

    def _focus(self) -> list[int]:
        """The current pair: the scan being matched and the model scan nearest it in the sequence."""
        if self.current is None:
            return []
        nearest = min(self.model, key=lambda m: abs(m - self.current), default=None)  # type: ignore[operator]
        return [self.current] if nearest is None else [self.current, nearest]

    def _show(self, event: Event) -> None:
        viewer = self.viewer
        status = viewer.controls.step_status
        self.events += 1
        if isinstance(event, ScanStarted):
            self._set_pair(int(event.index), [int(i) for i in event.model_indices])
            self.history = []
            viewer.set_poses(self._pose_list(event.index, event.initial), [event.index])
        elif isinstance(event, IcpIterated):
            it = event.iteration
            self.history.append((int(it.index), float(it.rms), int(it.pairs)))
            viewer.set_poses(self._pose_list(event.index, event.pose), [event.index])
            self._draw_correspondences(int(event.index), float(it.max_distance))
            viewer.controls.show_icp_history(self.history)
            status.content = f"scan {event.index} · iteration {it.index} · RMS {it.rms:.4f} m · {it.pairs} pairs"
        elif isinstance(event, ScanRegistered):
            viewer.set_poses(self._pose_list(event.index, event.pose), [event.index])
            status.content = f"scan {event.index} registered (RMS {event.result.rms:.4f} m)"
        elif isinstance(event, ScanSkipped):
            viewer.set_poses(self._pose_list(event.index, event.pose), [event.index])
            status.content = f"{event.reason}; going on from its predicted pose"
        elif isinstance(event, Finished):
            self.finished = True
            self._set_pair(None, [])
            viewer.server.scene.add_line_segments(
                "/correspondences", np.zeros((1, 2, 3), np.float32), colors=(0, 0, 0), visible=False
            )
            self.run.store()
            status.content = "registration finished; stored as a new revision"
        elif isinstance(event, LoopsDetected):
            accepted = sum(1 for h in event.hypotheses if h.accepted)
            status.content = f"{len(event.hypotheses)} loop hypotheses, {accepted} accepted"
        elif isinstance(event, LoopClosed):
            viewer.set_poses([np.asarray(p) for p in self.pipeline.poses])
            status.content = (
                f"loop {event.loop.i}-{event.loop.j} closed; largest move {max(event.displacement, default=0):.2f} m"
            )
        elif isinstance(event, RelaxationProgressed):
            viewer.set_poses([np.asarray(p) for p in self.pipeline.poses])
            status.content = f"relaxation iteration {event.iteration}: residual {100 * event.residual:.2f} cm"

    def _pose_list(self, index: int, pose: Any) -> list[Matrix]:
        poses = [np.eye(4)] * (index + 1)
        poses[index] = np.asarray(pose, dtype=np.float64)
        return poses

    def _set_pair(self, current: int | None, model: list[int]) -> None:
        viewer = self.viewer
        self.current, self.model = current, model
        viewer.colouring.set_highlight(display.pair_colours(current, model))
        if self._playing.is_set():
            viewer.begin_playback(self._focus())

    def _draw_correspondences(self, index: int, max_distance: float) -> None:
        """Closest-point pairs between the current scan and its model, from the displayed points (capped)."""
        viewer = self.viewer
        if not self.model or max_distance <= 0:
            return
        world = [
            viewer.scans.local[m].astype(np.float64) @ viewer.scans.poses[m][:3, :3].T + viewer.scans.poses[m][:3, 3]
            for m in self.model
        ]
        model = np.concatenate(world)
        data = viewer.scans.local[index].astype(np.float64)
        pose = viewer.scans.poses[index]
        data_idx, model_idx = correspondences(model, data, pose, max_distance, limit=MAX_CORRESPONDENCES)
        if len(data_idx) == 0:
            return
        origin = viewer.scans.poses[0][:3, 3]
        start = data[data_idx] @ pose[:3, :3].T + pose[:3, 3] - origin
        end = model[model_idx] - origin
        viewer.server.scene.add_line_segments(
            "/correspondences",
            np.stack([start, end], axis=1).astype(np.float32),
            colors=(255, 255, 0),
            thickness=1.0,
            thickness_units="screen",
            position=origin,
        )
