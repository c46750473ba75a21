"""The 3D view of a session: one viser server per open session, shared by every browser on it.

Everything shown lives in server-side state, so a second browser on the same session sees the
same map, colours and revision. Scans are sent (display-reduced to a point budget, coarse first)
in their own frame; moving a scan only changes its scene node's pose.
"""

from __future__ import annotations

import threading
import time
import traceback
from typing import Any

import numpy as np
import viser

from app import render_panel, scene
from app.editing import editor_for
from app.jobs import JobConflictError
from app.panels import build_panels
from app.panels.progress import show_job_progress
from app.registration import pipeline_config
from app.stepper import Stepper
from app.workbench import Workbench
from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix, rotation_to_quaternion
from slam6d.session import CACHE_DIR

COLOUR_MODES = ("scan", "height", "residual")
# what a button press may run into that the user can act on: shown as the message alone
USER_ERRORS = (Slam6dError, ValueError, FileExistsError, JobConflictError)
_CLIENT_WAIT = 5.0  # s: how long the full pass waits for the browser that opened the session to connect
_COARSE_SETTLE = 0.5  # s: time for a browser to take in the coarse pass before the full one follows


class SessionViewer:
    def __init__(self, workbench: Workbench, session_id: str) -> None:
        self.workbench = workbench
        self.session_id = session_id
        self.state = workbench.state(session_id)
        self.editor = editor_for(workbench)
        self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False, label=self.state.session.name)
        self.port = self.server.get_port()
        self.server.scene.set_up_direction("+z")
        # no shadow maps: points neither cast nor receive shadows, and rendering the light's shadow
        # cascades is a fixed cost on every frame (large without a GPU)
        self.server.scene.configure_default_lights(cast_shadow=False)
        self.server.gui.configure_theme(dark_mode=True, control_width="large")
        self.lock = threading.RLock()
        self.ready = threading.Event()
        self.error: str | None = None
        self.stopped = False
        self.local: list[np.ndarray] = []  # display points per scan, scanner frame, float32
        self.poses: list[Matrix] = []
        self.nodes: list[Any] = []
        self.light: dict[int, tuple[Any, np.ndarray]] = {}  # playback: scan -> (light node, its point indices)
        self.focus: list[int] | None = None  # while stepping plays: the scans drawn in full
        self.residuals: list[np.ndarray] | None = None
        self.highlight: dict[int, tuple[int, int, int]] = {}
        self.selected: dict[int, tuple[int, int, int]] = {}  # scans picked for editing; drawn over highlight
        self.pose_version = 0  # counts changes of the shown poses: what edge residuals were computed for
        self.edge_residuals: dict[tuple[int, int], float] = {}
        self.edge_residual_version = -1
        self.edge_nodes: dict[str, list[Any]] = {}  # "all": the line nodes drawn, one per edge colour
        self.edge_colours: dict[str, np.ndarray] = {}  # per kind ("/graph/trajectory", "/graph/loops"), per edge
        # red from a quarter of the ICP pairing distance: an edge's point-to-plane residual (upper
        # quartile) sits near the range noise when its scans agree and reaches centimetres at
        # odometry-level errors
        self.edge_scale = float(pipeline_config(self.state.session.config.engine).icp.max_distance) / 4
        self._edges_wanted = threading.Event()
        self._edges_worker: threading.Thread | None = None
        self._height_range = (0.0, 1.0)
        self.shown_revision = -1
        self.coarse_points = 0  # points of the coarse first pass (0: the budget was sent in one pass)
        self.pose_updates = 0
        self.stepper: Stepper | None = None
        self.client_names: dict[int, Any] = {}
        self._client_seen = threading.Event()
        self._build_gui()
        self.render_panel = render_panel.RenderPanel(self)  # the "Fly-through" folder
        self.panels = build_panels(self)  # loops, graph edits, octree guess, replay (app/panels)
        self.server.on_client_connect(self._on_connect)
        threading.Thread(target=self._load, name=f"viewer-load-{session_id}", daemon=True).start()

    # -------------------------------------------------------------- GUI

    def _build_gui(self) -> None:
        gui = self.server.gui
        self.status = gui.add_markdown("Loading scans…")
        self.warnings = gui.add_markdown("")
        self.progress = gui.add_progress_bar(0.0, animated=True)
        with gui.add_folder("View"):
            self.colour = gui.add_dropdown("Colour by", COLOUR_MODES, initial_value="scan")
            self.point_size = gui.add_slider("Point size", 0.005, 0.2, 0.005, 0.03)
            self.budget = gui.add_number("Point budget", scene.DEFAULT_BUDGET, min=10_000, max=20_000_000, step=10_000)
            self.apply_budget = gui.add_button("Apply budget")
            self.show_trajectory = gui.add_checkbox("Trajectory", True)
            self.show_edges = gui.add_checkbox("Graph edges", True)
            self.edge_legend = gui.add_markdown("")
        with gui.add_folder("Registration"):
            self.run_button = gui.add_button("Run registration")
            self.cancel_button = gui.add_button("Cancel job", disabled=True)
            self.step_button = gui.add_button("Step ICP iteration")
            self.next_scan_button = gui.add_button("Next scan")
            self.play_button = gui.add_button("Play")
            self.pause_button = gui.add_button("Pause", disabled=True)
            self.step_status = gui.add_markdown("")
            self.plot = gui.add_uplot(
                (np.zeros(0), np.zeros(0), np.zeros(0)),
                (
                    {"label": "iteration"},
                    {"label": "RMS (m)", "stroke": "#e8590c", "scale": "m"},
                    {"label": "pairs", "stroke": "#1c7ed6", "scale": "n"},
                ),
                title="ICP per iteration",
                scales={"x": {"time": False}, "m": {"auto": True}, "n": {"auto": True}},
                axes=({}, {"scale": "m"}, {"scale": "n", "side": 1}),
                aspect=1.6,
            )
        with gui.add_folder("History"):
            self.revision_text = gui.add_markdown("")
            self.undo_button = gui.add_button("Undo")
            self.redo_button = gui.add_button("Redo")

        self.colour.on_update(lambda _: self.run_safely(self.recolour))
        self.point_size.on_update(lambda _: self._set_point_size())
        self.apply_budget.on_click(lambda _: self.run_safely(self._rebuild_scans))
        self.show_trajectory.on_update(lambda _: self.draw_graph())
        self.show_edges.on_update(lambda _: self.draw_graph())
        self.undo_button.on_click(
            lambda e: self.run_safely(lambda: self.workbench.undo(self.session_id, self.author(e)))
        )
        self.redo_button.on_click(
            lambda e: self.run_safely(lambda: self.workbench.redo(self.session_id, self.author(e)))
        )
        self.run_button.on_click(lambda e: self.run_safely(lambda: self._start_registration(self.author(e))))
        self.cancel_button.on_click(lambda _: self._cancel_jobs())
        self.step_button.on_click(lambda e: self.run_safely(lambda: self._stepper(self.author(e)).step()))
        self.next_scan_button.on_click(lambda e: self.run_safely(lambda: self._stepper(self.author(e)).next_scan()))
        self.play_button.on_click(lambda e: self.run_safely(lambda: self._stepper(self.author(e)).play()))
        self.pause_button.on_click(lambda _: self._pause())

    def _on_connect(self, client: viser.ClientHandle) -> None:
        # Each browser has its own name field, so the journal records who pressed a button.
        self.client_names[client.client_id] = client.gui.add_text("Your name", f"guest-{client.client_id}", order=-1)
        self._client_seen.set()

    def author(self, event: Any) -> str:
        field = self.client_names.get(getattr(event, "client_id", -1))
        return (field.value.strip() if field is not None else "") or "anonymous"

    def run_safely(self, action: Any) -> None:
        """GUI callbacks and the panels' background refreshes: an error the user can act on becomes a
        visible warning, not a dead button; anything else also leaves its traceback in the log. Once the
        view has stopped nothing runs: its server would drop the updates."""
        if self.stopped:
            return
        try:
            action()
        except USER_ERRORS as exc:
            self.warn(str(exc))
        except Exception as exc:
            traceback.print_exc()
            self.warn(f"{type(exc).__name__}: {exc}")

    def warn(self, message: str) -> None:
        self.warnings.content = f"**⚠ {message}**" if message else ""

    # -------------------------------------------------------------- scene

    def _load(self) -> None:
        try:
            sequence = self.state.sequence(lambda d, t: self._progress("Reading scans", d, t))
            self.budget.value = int(self.state.session.config.engine.get("display_budget", scene.DEFAULT_BUDGET))  # type: ignore[misc]
            poses = sequence.poses()
            lo = np.min([p[:3, 3] for p in poses], axis=0)
            hi = np.max([p[:3, 3] for p in poses], axis=0)
            centre = (lo + hi) / 2
            size = max(float(np.linalg.norm(hi - lo)), 20.0)
            self.server.initial_camera.look_at = centre
            self.server.initial_camera.position = centre + np.array([-0.4, -0.6, 0.7]) * size
            self._rebuild_scans()
            self.progress.visible = False
        except Exception as exc:
            self.error = str(exc)
            self.status.content = f"**Cannot load this session:** {exc}"
            self.progress.visible = False
            if not isinstance(exc, Slam6dError):
                traceback.print_exc()
        finally:
            self.ready.set()

    def _progress(self, stage: str, done: int, total: int) -> None:
        self.progress.value = 100.0 * done / max(total, 1)  # type: ignore[misc]
        self.status.content = f"{stage}… {done}/{total}"

    def _rebuild_scans(self) -> None:
        """(Re)send every scan at the current budget: the only time point data goes over the wire.

        Two passes when the budget is above :data:`scene.COARSE_BUDGET`: first every scan at a
        coarse level, so the whole map is on screen after one cheap frame (without a GPU a frame
        costs ~2 µs per point), then every scan at the full budget, replacing the coarse points.
        Each pass is one atomic batch, so a browser draws the map once per pass, complete,
        rather than redrawing a growing map after each scan. (Sending a remembered full selection
        in one pass was tried: its larger message reaches a busy browser seconds later than the
        coarse one, and the full frame came no sooner.)
        """
        sequence = self.state.sequence()
        clouds = [s.points for s in sequence.scans]
        names = [s.name for s in sequence.scans]
        budget = int(self.budget.value)
        voxel = float(self.state.session.config.engine.get("display_voxel_size", 0.05))
        self.coarse_points, coarse_sent = 0, 0.0
        if budget > scene.COARSE_BUDGET and sum(len(c) for c in clouds) > scene.COARSE_BUDGET:
            self._show_selection(sequence, scene.coarse_selection(clouds), names, replace=True)
            coarse_sent = time.monotonic()
            self.coarse_points = sum(len(p) for p in self.local)
            self.status.content = (
                f"**{self.state.session.name}** · {len(self.local)} scans · coarse view "
                f"({self.coarse_points:,} points), loading full detail…"
            )
            self.draw_graph()
        selection = scene.cached_budget_selection(
            self.state.session.folder / CACHE_DIR / "display.npz", clouds, budget, voxel
        )
        if self.coarse_points:
            self._let_browsers_draw_coarse(coarse_sent)
        self._show_selection(sequence, selection, names, replace=not self.coarse_points)
        self.draw_graph()
        self._update_status()

    def _let_browsers_draw_coarse(self, sent: float) -> None:
        """Hold the full pass until the browser has the coarse one in a batch of its own.

        The viewer starts on the request for the session page, typically before that page's 3D
        view connects; a browser connecting after both passes were sent would get only the full
        one and draw nothing for seconds. Nobody connecting within :data:`_CLIENT_WAIT` means
        nobody is waiting for a first look.
        """
        if not self._client_seen.wait(max(0.0, sent + _CLIENT_WAIT - time.monotonic())):
            return
        time.sleep(_COARSE_SETTLE)

    def _show_selection(self, sequence: Any, selection: list[np.ndarray], names: list[str], replace: bool) -> None:
        """Display ``selection`` of each scan; ``replace`` drops the old nodes (and their poses) first.

        Without ``replace`` the scans keep the poses they are shown at, which may have moved
        (ICP stepping) since the previous pass was sent.
        """
        with self.lock:
            self.local = [s.points[idx].astype(np.float32) for s, idx in zip(sequence.scans, selection, strict=True)]
            if replace or len(self.poses) != len(self.local):
                self.poses = [s.pose.copy() for s in sequence.scans]
                self.pose_version += 1
            self.residuals = None
            if self.colour.value == "height":
                self._height_range = scene.height_range(self.local, self.poses)
            self._send_scans(names, replace)
            self.shown_revision = self.state.session.revision

    def _send_scans(self, names: list[str], replace: bool = True) -> None:
        """All scans in one websocket message, so the browser's first frame with points shows them all.

        A node added under an existing name takes the old one's place in the same batch, so a
        second pass never leaves a frame with a scan missing.

        viser sends at most 128 messages (4 per scan) per websocket message and the browser
        redraws after each one; the window is widened to hold the whole map. (Hiding the scans
        until all are sent does not work: viser drops a queued "hidden" when "shown" follows.)
        """
        buffer = self.server._websock_server.get_message_buffer()  # no public setting for this
        buffer.max_window_size = max(buffer.max_window_size, 4 * len(self.local) + 1024)  # + a new client's GUI backlog
        with self.server.atomic():
            if replace:
                for node in self.nodes:
                    node.remove()
            for node, _ in self.light.values():
                node.remove()
            self.nodes, self.light = [], {}
            for k, points in enumerate(self.local):
                pose = self.poses[k]
                self.nodes.append(
                    self._add_cloud(
                        f"/scans/{names[k] or k}",
                        points,
                        self.scan_colours(k),
                        pose,
                        precision=scene.precision_for(points),
                        visible=self.focus is None or k in self.focus,
                    )
                )
            if self.focus is not None:
                self._show_focus(self.focus)

    def begin_playback(self, focus: list[int]) -> None:
        """Stepping plays: draw ``focus`` (the current pair) in full and the rest of the map light.

        Without a GPU a frame costs about a microsecond or two per point, so with the whole budget
        on screen a browser draws one pose in seconds and falls behind the stepping; with the light
        map it keeps up. The light points are a subset of the displayed ones, sent once as nodes of
        their own next to the full ones: switching is a visibility change, nothing is re-sent.
        """
        self._show_focus(focus)

    def end_playback(self) -> None:
        """Back to the whole map at the full budget (the full nodes were kept, hidden)."""
        with self.lock, self.server.atomic():
            self.focus = None
            for k, node in enumerate(self.nodes):
                node.visible = True
                if k in self.light:
                    self.light[k][0].visible = False

    def _show_focus(self, focus: list[int]) -> None:
        with self.lock, self.server.atomic():
            self.focus = list(focus)
            share = max(1, scene.PLAYBACK_BUDGET // max(1, len(self.nodes)))
            for k, node in enumerate(self.nodes):
                full = k in self.focus
                node.visible = full
                if not full and k not in self.light:
                    keep = scene.display_indices(self.local[k], 0.0, share)
                    pose = self.poses[k]
                    light = self._add_cloud(
                        f"/light/{k}",
                        self.local[k][keep],
                        self._light_colours(self.scan_colours(k), keep),
                        pose,
                        precision=scene.precision_for(self.local[k]),  # the full scan's, so both nodes match
                    )
                    self.light[k] = (light, keep)
                if k in self.light:
                    if not full:
                        self._place(self.light[k][0], self.poses[k])
                    self.light[k][0].visible = not full

    def _add_cloud(
        self,
        name: str,
        points: np.ndarray,
        colours: np.ndarray | tuple[int, int, int],
        pose: Matrix,
        precision: str,
        visible: bool = True,
    ) -> Any:
        """A scan's points in its own frame, placed by its pose on the node (never world coordinates)."""
        return self.server.scene.add_point_cloud(
            name,
            points=points,
            colors=colours,
            point_size=float(self.point_size.value),
            point_shading="flat",  # no per-pixel sphere shading: ~15 % faster frames without a GPU
            precision=precision,  # type: ignore[arg-type]
            position=pose[:3, 3],
            wxyz=rotation_to_quaternion(pose[:3, :3]),
            visible=visible,
        )

    @staticmethod
    def _light_colours(colours: np.ndarray | tuple[int, int, int], keep: np.ndarray) -> np.ndarray:
        array = np.asarray(colours, np.uint8)
        return array[keep] if array.ndim == 2 else array

    def scan_colours(self, k: int) -> np.ndarray | tuple[int, int, int]:
        if k in self.selected:
            return self.selected[k]
        if k in self.highlight:
            return self.highlight[k]
        mode = self.colour.value
        if mode == "height":
            low, high = self._height_range
            return scene.ramp(scene.world_heights(self.local[k], self.poses[k]), low, high)
        if mode == "residual" and self.residuals is not None:
            return scene.ramp(self.residuals[k], 0.0, 0.3)
        return scene.scan_color(k)

    def recolour(self) -> None:
        with self.lock:
            if self.colour.value == "height":
                self._height_range = scene.height_range(self.local, self.poses)
            if self.colour.value == "residual" and self.residuals is None:
                self.status.content = "Computing residuals…"
                self.residuals = scene.residuals(self.local, self.poses)
            with self.server.atomic():
                for k in range(len(self.nodes)):
                    self.paint(k)
        self._update_status()

    def paint(self, k: int) -> None:
        """Send scan ``k``'s colours; a single colour goes as one RGB triple, not one per point."""
        colours = np.asarray(self.scan_colours(k), np.uint8)
        self.nodes[k].colors = colours
        if k in self.light:
            node, keep = self.light[k]
            node.colors = self._light_colours(colours, keep)

    def pick(self, ray_origin: Any, ray_direction: Any) -> int | None:
        """The scan under a click: tested on the displayed points at the poses shown."""
        with self.lock:
            return scene.pick_scan(self.local, self.poses, ray_origin, ray_direction)

    def select(self, selected: dict[int, tuple[int, int, int]]) -> None:
        """Mark scans picked for editing in their own colour; only scans whose colour changes are resent."""
        with self.lock, self.server.atomic():
            changed = set(self.selected) ^ set(selected) | {k for k in selected if self.selected.get(k) != selected[k]}
            self.selected = dict(selected)
            for k in changed:
                if k < len(self.nodes):
                    self.paint(k)

    def _set_point_size(self) -> None:
        for node in [*self.nodes, *(light for light, _ in self.light.values())]:
            node.point_size = float(self.point_size.value)

    def set_poses(self, poses: list[Matrix], indices: list[int] | None = None) -> None:
        """Move scan nodes: only position and orientation of the nodes that moved are sent.

        One atomic batch, so a browser never draws a scan at a new position with its old rotation.
        """
        with self.lock, self.server.atomic():
            if self.stopped:  # a stepper or replay thread may still be mid-step when the view stops
                return
            moved = False
            for k in range(len(poses)) if indices is None else indices:
                pose = np.asarray(poses[k], dtype=np.float64)
                if k >= len(self.nodes) or np.array_equal(pose, self.poses[k]):
                    continue
                self.poses[k] = pose.copy()
                self._place(self.nodes[k], pose)
                if k in self.light and self.focus is not None and k not in self.focus:
                    self._place(self.light[k][0], pose)  # a hidden light node is placed when shown
                moved = True
            self.pose_updates += 1
            if moved:
                self.residuals = None
                self.pose_version += 1

    @staticmethod
    def _place(node: Any, pose: Matrix) -> None:
        node.position = pose[:3, 3]
        node.wxyz = rotation_to_quaternion(pose[:3, :3])

    def draw_graph(self) -> None:
        """Trajectory (sequential edges) and loop edges, each coloured by its point-to-plane residual.

        The residuals are the editor's per-edge summary (the numbers the "residuals jumped" guardrail
        compares), computed in the background for the poses shown; until they are in, edges are grey.
        """
        with self.lock:
            if not self.poses:
                return
            origin = self.poses[0][:3, 3]
            edges = [(e["i"], e["j"], e["kind"]) for e in self.editor.edges(self.session_id)]
            edges = [e for e in edges if e[0] < len(self.poses) and e[1] < len(self.poses)]
            known = self.edge_residuals if self.edge_residual_version == self.pose_version else None
            for node in self.edge_nodes.pop("all", []):
                node.remove()
            drawn: list[Any] = []
            for name, sequential, thickness, toggle in (
                ("/graph/trajectory", True, 3.0, self.show_trajectory),
                ("/graph/loops", False, 4.0, self.show_edges),
            ):
                chosen = [(i, j) for i, j, kind in edges if (kind == "sequential") == sequential]
                if known is None:
                    colours = np.full((len(chosen), 3), 150, np.uint8)
                else:
                    residuals = [known.get((i, j), np.nan) for i, j in chosen]
                    colours = scene.edge_colours(residuals, self.edge_scale)[:, 0]
                self.edge_colours[name] = colours
                segments = scene.segments(chosen, self.poses)
                # one node per colour: viser's line segments take one colour per node reliably (its
                # per-vertex uint8 colours reach the browser's line material unnormalised, as white)
                shades, which = np.unique(colours, axis=0, return_inverse=True) if chosen else (colours, [])
                for b, shade in enumerate(shades):
                    drawn.append(
                        self.server.scene.add_line_segments(
                            f"{name}/{b}",
                            segments[np.asarray(which).reshape(-1) == b],
                            colors=scene.rgb(shade),
                            thickness=thickness,
                            thickness_units="screen",
                            position=origin,
                            visible=bool(toggle.value),
                        )
                    )
            self.edge_nodes["all"] = drawn
            if known is None:
                self._edge_residuals_later()
            self._edge_legend(known)

    def _edge_residuals_later(self) -> None:
        """Compute the edges' residuals for the shown poses in the background, then recolour them.

        The first call builds the editor's reduced scans (seconds for a large session, paid once and
        reused by every edit), so it never holds up the map. Requests while one runs coalesce.
        """
        self._edges_wanted.set()
        if self._edges_worker is not None and self._edges_worker.is_alive():
            return

        def work() -> None:
            self.ready.wait()  # after the full map is sent: the first look at a session comes first
            while self._edges_wanted.is_set() and not self.stopped:
                self._edges_wanted.clear()
                with self.lock:
                    version, poses = self.pose_version, [p.copy() for p in self.poses]
                try:
                    summary = self.editor.residuals(self.session_id, poses)
                    with self.lock:
                        if self.stopped:
                            return
                        if version != self.pose_version:
                            continue  # moved meanwhile: the next request (or a redraw) computes them
                        self.edge_residuals = {(int(e["i"]), int(e["j"])): float(e["plane"]) for e in summary.edges}
                        self.edge_residual_version = version
                        self.draw_graph()
                except Exception as exc:
                    if not self.stopped:
                        self.edge_legend.content = f"Edge residuals unavailable: {exc}"
                    return

        self._edges_worker = threading.Thread(target=work, name=f"edge-residuals-{self.session_id}", daemon=True)
        self._edges_worker.start()

    def _edge_legend(self, known: dict[tuple[int, int], float] | None) -> None:
        low, high = (f"rgb{tuple(int(c) for c in rgb[0])}" for rgb in scene.edge_colours([0, 1], 1.0))
        scale = (
            f"Edges by point-to-plane residual (upper quartile): <span style='color:{low}'>■</span> 0 m → "
            f"<span style='color:{high}'>■</span> ≥ {self.edge_scale:.2f} m or no overlap"
        )
        if known is None:
            self.edge_legend.content = f"{scale} · computing…"
            return
        finite = {edge: rms for edge, rms in known.items() if np.isfinite(rms)}
        worst = max(known, key=lambda e: np.inf if not np.isfinite(known[e]) else known[e], default=None)
        detail = ""
        if worst is not None:
            value = known[worst]
            detail = f" · worst {worst[0]}–{worst[1]}: " + (f"{value:.3f} m" if np.isfinite(value) else "no overlap")
        if finite:
            detail += f" · median {np.median(list(finite.values())):.3f} m"
        self.edge_legend.content = scale + detail

    def _update_status(self) -> None:
        session = self.state.session
        shown = sum(len(p) for p in self.local)
        total = sum(len(s) for s in self.state.sequence().scans)
        self.status.content = (
            f"**{session.name}** · {len(self.local)} scans · {shown:,} of {total:,} points shown · "
            f"revision {session.revision}"
        )
        self.revision_text.content = (
            f"Revision {session.revision} (undo: {session.journal.can_undo()}, redo: {session.journal.can_redo()})"
        )

    def on_revision(self) -> None:
        """The journal's current revision changed (edit, undo, job): show it."""
        if not self.ready.is_set() or self.error:
            return
        poses = self.state.session.poses()
        self.set_poses(poses)
        with self.lock:
            self.shown_revision = self.state.session.revision
            if self.colour.value != "scan":
                self.recolour()
        self.draw_graph()
        self._update_status()
        for panel in self.panels:
            self.run_safely(panel.refresh)

    # -------------------------------------------------------------- jobs

    def _start_registration(self, author: str) -> None:
        from app.registration import registration_job

        work = registration_job(self.workbench, self.session_id, author, {})
        self.workbench.jobs.submit(self.session_id, "register", work, author)

    def _cancel_jobs(self) -> None:
        for job in self.workbench.jobs.for_session(self.session_id):
            self.workbench.jobs.cancel(job.id)

    def on_job(self, job: Any) -> None:
        show_job_progress(job, self.run_button, self.cancel_button, self.progress, self.status, job.kind)
        if job.active:
            return
        if job.status == "failed":
            self.warn(f"{job.kind} failed: {job.message}")
            self._update_status()
        else:
            # an edit's guardrail (e.g. residuals jumped) stays visible after the job
            self.warn((job.result.get("warning") or "") if job.status == "done" else f"{job.kind} {job.status}")
            self._update_status()

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
            "scans": len(self.nodes),
            "points_shown": int(sum(len(p) for p in self.local)),
            "points_coarse": self.coarse_points,
            "colour": self.colour.value,
            "revision_shown": self.shown_revision,
            "pose_updates": self.pose_updates,
            "stepping": None if self.stepper is None else self.stepper.as_dict(),
            "clients": len(self.server.get_clients()),
        }

    def stop(self) -> None:
        with self.lock:  # no background drawing is half-way when the server goes
            self.stopped = True
        if self.stepper is not None:
            self.stepper.pause()
        self.server.stop()


class ViewerRegistry:
    """Starts a session's viewer when someone first opens it; keeps it for everyone after."""

    def __init__(self, workbench: Workbench) -> None:
        self.workbench = workbench
        self._viewers: dict[str, SessionViewer] = {}
        self._lock = threading.Lock()
        workbench.on_revision(self._on_revision)
        workbench.jobs.on_change(self._on_job)

    def get(self, session_id: str) -> SessionViewer:
        with self._lock:
            viewer = self._viewers.get(session_id)
            if viewer is None:
                viewer = self._viewers[session_id] = SessionViewer(self.workbench, session_id)
            return viewer

    def existing(self, session_id: str) -> SessionViewer | None:
        return self._viewers.get(session_id)

    def _on_revision(self, session_id: str) -> None:
        viewer = self._viewers.get(session_id)
        if viewer is not None:
            viewer.on_revision()

    def _on_job(self, job: Any) -> None:
        viewer = self._viewers.get(job.session_id)
        if viewer is not None:
            viewer.on_job(job)

    def stop_all(self) -> None:
        with self._lock:
            for viewer in self._viewers.values():
                viewer.stop()
            self._viewers.clear()
