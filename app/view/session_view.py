"""The 3D view of a session: one viser server per open session, shared by every browser on it.

Everything shown lives in server-side state, so a second browser on the same session sees the
same map, colours and revision. The view is composed of parts, one module each, that share the
session (:class:`app.view.core.ViewContext`) and the scans as shown (:class:`app.view.core.ShownScans`)
and call each other only through the handles wired here:

* :mod:`app.view.scene_stream` - the scans sent at a point budget, coarse first, moved by pose;
* :mod:`app.view.detail_stream` - their levels of detail, following the camera;
* :mod:`app.view.colouring` - colours by scan, height or residual, picked and highlighted scans;
* :mod:`app.view.picking` - which scan is under a click;
* :mod:`app.view.playback` - the light map while registration is stepped;
* :mod:`app.view.graph_overlay` - trajectory and loop edges coloured by residual;
* :mod:`app.view.controls` - the View / Registration / History folders;
* :mod:`app.view.stepping` - registration one ICP iteration at a time;
* :mod:`app.view.presence` - who is on the view, their cameras, following;
* :mod:`app.view.panels` - loops, graph edits, octree guesses, replay, fly-through.
"""

from __future__ import annotations

import threading
from typing import Any

import viser

from app.editing import editor_for
from app.registration import registration_job
from app.view.colouring import Colouring
from app.view.core import ShownScans, ViewContext, show_status
from app.view.graph_overlay import GraphOverlay
from app.view.names import BrowserNames
from app.view.panels import Panel, build_panels
from app.view.panels.fly_through import FlyThroughPanel
from app.view.panels.progress import show_job_progress
from app.view.picking import Picking
from app.view.playback import Playback
from app.view.scene_stream import SceneStream
from app.view.stepping import Stepper
from app.workbench import Workbench
from slam6d.engine_settings import pipeline_config
from slam6d.geometry import Matrix


class SessionViewer(ViewContext):
    """The context every part shares, the parts, and the wiring between them and the controls."""

    def __init__(self, workbench: Workbench, session_id: str) -> None:
        state = workbench.state(session_id)
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False, label=state.session.name)
        super().__init__(workbench, session_id, editor_for(workbench), server)
        self.port = server.get_port()
        server.scene.set_up_direction("+z")
        # no shadow maps: points neither cast nor receive shadows, and rendering the light's shadow
        # cascades is a fixed cost on every frame (large without a GPU)
        server.scene.configure_default_lights(cast_shadow=False)
        server.gui.configure_theme(dark_mode=True, control_width="large")
        self.scans = ShownScans()
        self.colouring = Colouring(self, self.scans)
        self.playback = Playback(self, self.scans, self.colouring)
        icp_max_distance = float(pipeline_config(self.state.session.config.engine).icp.max_distance)
        self.graph = GraphOverlay(
            self,
            self.scans,
            icp_max_distance,
            lambda: None if self.stream.detail is None else self.stream.detail.levels,
        )
        self.fly_through: FlyThroughPanel | None = None  # the panels beyond viewing and registration,
        self.panels: list[Panel] = []  # added once the first look is out (_add_panels)
        self.stream = SceneStream(
            self, self.scans, self.colouring, self.playback.show_focus, self.graph.draw, self._add_panels
        )
        self.picking = Picking(self, self.scans)
        self.stepper: Stepper | None = None
        self.names = BrowserNames()  # who is behind each browser: the name typed in the page header
        self._wire_controls()
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(lambda client: self.names.client_left(client.client_id))
        threading.Thread(target=self.stream.load, name=f"viewer-load-{session_id}", daemon=True).start()

    def _add_panels(self) -> None:
        """The folders beyond viewing and registration: fly-through, loops, graph edits, octree guess,
        replay, components (:mod:`app.view.panels`). Added after the first look at the map went out
        (just before the full pass), so the batch a browser first draws the map from carries only the
        view's own controls: the panels' ~70 GUI elements cost a software-rendering browser ~0.15 s of
        its main thread, which then comes after the map is on screen."""
        with self.lock:  # (a view stopped while it loaded gets none: its server would drop them)
            if self.fly_through is not None or self.stopped:
                return
            self.fly_through = FlyThroughPanel(self)  # the "Fly-through" folder
            self.panels = build_panels(self)  # loops, graph edits, octree guess, replay (app/view/panels)

    def _wire_controls(self) -> None:
        c = self.controls
        c.colour.on_update(lambda _: self.run_safely(self.colouring.recolour))
        c.point_size.on_update(lambda _: self.stream.set_point_size())
        c.apply_budget.on_click(lambda _: self.run_safely(self.stream.rebuild_scans))
        c.show_trajectory.on_update(lambda _: self.graph.draw())
        c.show_edges.on_update(lambda _: self.graph.draw())
        c.undo_button.on_click(lambda e: self.run_safely(lambda: self.workbench.undo(self.session_id, self.author(e))))
        c.redo_button.on_click(lambda e: self.run_safely(lambda: self.workbench.redo(self.session_id, self.author(e))))
        c.run_button.on_click(lambda e: self.run_safely(lambda: self._start_registration(self.author(e))))
        c.cancel_button.on_click(lambda _: self._cancel_jobs())
        c.step_button.on_click(lambda e: self.run_safely(lambda: self._stepper(self.author(e)).step()))
        c.next_scan_button.on_click(lambda e: self.run_safely(lambda: self._stepper(self.author(e)).next_scan()))
        c.play_button.on_click(lambda e: self.run_safely(lambda: self._stepper(self.author(e)).play()))
        c.pause_button.on_click(lambda _: self._pause())

    # -------------------------------------------------------------- what callers outside the view use

    def set_poses(self, poses: list[Matrix], indices: list[int] | None = None) -> None:
        """Move scans (all, or those in ``indices``) to ``poses``: what stepping, replay and dragging call."""
        self.stream.set_poses(poses, indices)

    def begin_playback(self, focus: list[int]) -> None:
        self.playback.begin(focus)

    def end_playback(self) -> None:
        self.playback.end()

    # -------------------------------------------------------------- who acts

    def _on_connect(self, client: viser.ClientHandle) -> None:
        self.names.client_connected(client.client_id)
        self.stream.client_seen.set()

    def author(self, event: Any) -> str:
        """Who pressed a button: the name the person's page carries (the journal records it)."""
        return self.names.of(getattr(event, "client_id", None))

    def on_revision(self) -> None:
        """The journal's current revision changed (edit, undo, job): show it."""
        if not self.ready.is_set() or self.error:
            return
        poses = self.state.session.poses()
        self.set_poses(poses)
        with self.lock:
            self.stream.shown_revision = self.state.session.revision
            if self.controls.colour.value != "scan":
                self.colouring.recolour()
        self.graph.draw()
        show_status(self, self.scans)
        for panel in self.panels:
            self.run_safely(panel.refresh)

    # -------------------------------------------------------------- jobs and stepping

    def _start_registration(self, author: str) -> None:
        work = registration_job(self.workbench, self.session_id, author, {})
        self.workbench.jobs.submit(self.session_id, "register", work, author)

    def _cancel_jobs(self) -> None:
        for job in self.workbench.jobs.for_session(self.session_id):
            self.workbench.jobs.cancel(job.id)

    def on_job(self, job: Any) -> None:
        c = self.controls
        show_job_progress(job, c.run_button, c.cancel_button, c.progress, c.status, job.kind)
        if job.active:
            return
        if job.status == "failed":
            self.warn(f"{job.kind} failed: {job.message}")
        else:
            # an edit's guardrail (e.g. residuals jumped) stays visible after the job
            self.warn((job.result.get("warning") or "") if job.status == "done" else f"{job.kind} {job.status}")
        show_status(self, self.scans)

    def _pause(self) -> None:
        if self.stepper is not None:
            self.stepper.pause()

    def _stepper(self, author: str) -> Stepper:
        if self.stepper is None or self.stepper.finished:
            self.stepper = Stepper(self, author)
        return self.stepper

    def as_dict(self) -> dict[str, Any]:
        return {
            "ready": self.ready.is_set(),
            "error": self.error,
            "scans": len(self.scans.nodes),
            "points_shown": self.scans.points_shown(),
            "points_coarse": self.stream.coarse_points,
            "colour": self.controls.colour.value,
            "revision_shown": self.stream.shown_revision,
            "pose_updates": self.stream.pose_updates,
            "detail": None if self.stream.detail is None else self.stream.detail.as_dict(),
            "stepping": None if self.stepper is None else self.stepper.as_dict(),
            "clients": len(self.server.get_clients()),
        }

    def stop(self) -> None:
        with self.lock:  # no background drawing is half-way when the server goes
            self.stopped = True
        if self.stepper is not None:
            self.stepper.pause()
        self.server.stop()
