"""An older revision drawn as it was: a read-only 3D view of its own, with a private scene per browser.

The session's live 3D view (:mod:`app.view.session_view`) shows the head to everyone on it; a
permalink to an older revision must show that revision to the browser that opened it without
moving anyone else's map. Such a browser's 3D view therefore connects to a :class:`RevisionView`:
its own viser server drawing the scans (at the levels of detail of the live view's first look)
at the revision's poses and its pose-graph edges. Everything is added to each browser's *own*
scene (``client.scene``), so each browser on it has its own colour mode and selection marker (:mod:`app.view.selection_marker`).

It is read-only by construction: it has no edit controls, and its websocket is forwarded with a
viewer's rights (:mod:`app.view_roles`), so nothing a browser sends reaches it but its camera.
Views nobody has looked at for :data:`IDLE_STOP` seconds are stopped; at most
:data:`MAX_VIEWS` are open per server.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from app.errors import EditError
from app.view import display
from app.view.detail_levels import choose_levels
from app.view.presence import presence_of
from app.workbench import SessionState, Workbench
from slam6d.geometry import Matrix, rotation_to_quaternion
from slam6d.scan_levels import session_levels
from slam6d.session_graph import graph_edge_list

IDLE_STOP = 120.0  # s without a browser before an old revision's view is stopped
MAX_VIEWS = 8  # old revisions open at once on one server (each holds a coarse copy of the map)
EDGE_COLOURS = {"sequential": (150, 150, 150), "loop": (255, 138, 31), "manual": (80, 200, 255)}


@dataclass
class BrowserScene:
    """One browser's own scene of the revision: its scan nodes and colour mode."""

    client: Any  # viser ClientHandle
    nodes: list[Any] = field(default_factory=list)
    colour: str = "scan"


class RevisionView:
    """Revision ``revision`` of a session, drawn read-only for each browser that connects."""

    def __init__(self, state: SessionState, revision: int) -> None:
        self.state = state
        self.session_id = state.session.id
        self.revision = revision
        found = state.session.get_revision(revision)
        self.poses: list[Matrix] = [np.asarray(p, dtype=np.float64) for p in found.poses]
        self.edges = [(int(e["i"]), int(e["j"]), str(e["kind"])) for e in graph_edge_list(len(self.poses), found.graph)]
        # the live view's first look: every scan at the levels of detail that fit the coarse budget,
        # read as prefixes of the session's level store (built by the live view, or here if absent)
        levels = session_levels(state.session, lambda: state.sequence().scans)
        chosen = choose_levels(levels.level_points, np.ones(len(levels)), display.COARSE_BUDGET)
        self.local = [levels.points(k, level) for k, level in enumerate(chosen)]
        self.bounds = [(c.min(axis=0), c.max(axis=0)) if len(c) else (np.zeros(3), np.zeros(3)) for c in self.local]
        self._residuals: list[np.ndarray] | None = None
        self._components = _components(len(self.poses), [(i, j) for i, j, _ in self.edges])
        self._height_range = display.height_range(self.local, self.poses)
        self.lock = threading.RLock()
        self.browsers: dict[int, BrowserScene] = {}
        self.last_seen = time.monotonic()
        self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False, label=f"revision {revision}")
        self.port = self.server.get_port()
        self.server.scene.set_up_direction("+z")
        self.server.scene.configure_default_lights(cast_shadow=False)
        self.server.gui.configure_theme(dark_mode=True, control_width="large")
        self.server.gui.add_markdown(
            f"**{state.session.name} · revision {revision}** (read-only) · {len(self.local)} scans · "
            f"{sum(len(p) for p in self.local):,} points shown: the map as it was then. "
            "The page's banner leads to the current revision."
        )
        positions = np.array([p[:3, 3] for p in self.poses]) if self.poses else np.zeros((1, 3))
        lo, hi = positions.min(axis=0), positions.max(axis=0)
        size = max(float(np.linalg.norm(hi - lo)), 20.0)
        self.server.initial_camera.look_at = (lo + hi) / 2
        self.server.initial_camera.position = (lo + hi) / 2 + np.array([-0.4, -0.6, 0.7]) * size
        presence_of(self)  # who is who: before any browser connects
        self.server.on_client_connect(self._connected)
        self.server.on_client_disconnect(self._disconnected)

    # -------------------------------------------------------------- each browser's scene

    def _connected(self, client: Any) -> None:
        browser = BrowserScene(client)
        with self.lock:
            self.browsers[client.client_id] = browser
            self.last_seen = time.monotonic()
        with client.atomic():
            for k, points in enumerate(self.local):
                pose = self.poses[k]
                browser.nodes.append(
                    client.scene.add_point_cloud(
                        f"/scans/{k}",
                        points=points,
                        colors=self._colours(k, browser.colour),
                        point_size=0.03,
                        point_shading="flat",
                        precision=display.precision_for(points),
                        position=pose[:3, 3],
                        wxyz=rotation_to_quaternion(pose[:3, :3]),
                    )
                )
            for kind, colour in EDGE_COLOURS.items():
                pairs = [(i, j) for i, j, k in self.edges if k == kind]
                if pairs:
                    client.scene.add_line_segments(
                        f"/graph/{kind}",
                        display.segments(pairs, self.poses),
                        colors=colour,
                        thickness=3.0 if kind == "sequential" else 4.0,
                        thickness_units="screen",
                        position=self.poses[0][:3, 3],
                    )

    def _disconnected(self, client: Any) -> None:
        with self.lock:
            self.browsers.pop(client.client_id, None)
            self.last_seen = time.monotonic()

    def _colours(self, k: int, mode: str) -> np.ndarray | tuple[int, int, int]:
        if mode == "height":
            low, high = self._height_range
            return display.ramp(display.world_heights(self.local[k], self.poses[k]), low, high)
        if mode == "residual":
            if self._residuals is None:
                self._residuals = display.residuals(self.local, self.poses)
            return display.ramp(self._residuals[k], 0.0, 0.3)
        if mode == "component":
            return display.scan_color(self._components[k])
        return display.scan_color(k)

    def browser(self, client_id: int) -> BrowserScene:
        with self.lock:
            found = self.browsers.get(client_id)
        if found is None:
            raise EditError("that browser has left this revision's view", 404)
        return found

    def set_colour(self, client_id: int, mode: str) -> None:
        """Colour one browser's scans by ``mode``; nobody else's view changes."""
        browser = self.browser(client_id)
        with self.lock:
            colours = [np.asarray(self._colours(k, mode), np.uint8) for k in range(len(self.local))]
            browser.colour = mode
        with browser.client.atomic():
            for node, colour in zip(browser.nodes, colours, strict=True):
                node.colors = colour

    def as_dict(self) -> dict[str, Any]:
        """What this view draws: its revision and each scan's position there (the page and tests read it)."""
        with self.lock:
            colours = {str(cid): b.colour for cid, b in self.browsers.items()}
        return {
            "ready": True,
            "revision_shown": self.revision,
            "read_only": True,
            "scans": len(self.poses),
            "points_shown": int(sum(len(p) for p in self.local)),
            "positions": [[float(v) for v in p[:3, 3]] for p in self.poses],
            "colours": colours,
            "clients": len(self.browsers),
        }

    def stop(self) -> None:
        self.server.stop()


def _components(count: int, pairs: list[tuple[int, int]]) -> list[int]:
    """Connected component of each scan under the revision's graph edges, numbered from the first scan on."""
    parent = list(range(count))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for i, j in pairs:
        parent[root(i)] = root(j)
    numbers: dict[int, int] = {}
    return [numbers.setdefault(root(k), len(numbers)) for k in range(count)]


class RevisionViews:
    """The old revisions open on a server: started when a link first asks, stopped after nobody looks."""

    def __init__(self, workbench: Workbench) -> None:
        self.workbench = workbench
        self._views: dict[tuple[str, int], RevisionView] = {}
        self._lock = threading.Lock()

    def get(self, session_id: str, revision: int) -> RevisionView:
        self._stop_idle()
        with self._lock:
            view = self._views.get((session_id, revision))
            if view is not None:
                view.last_seen = time.monotonic()
                return view
            if len(self._views) >= MAX_VIEWS:
                raise EditError(
                    f"{MAX_VIEWS} old revisions are open on this server already; try again in a few minutes", 409
                )
            view = self._views[(session_id, revision)] = RevisionView(self.workbench.state(session_id), revision)
            return view

    def of_session(self, session_id: str) -> list[RevisionView]:
        with self._lock:
            return [v for (s, _), v in self._views.items() if s == session_id]

    def _stop_idle(self) -> None:
        now = time.monotonic()
        with self._lock:
            idle = [k for k, v in self._views.items() if not v.browsers and now - v.last_seen > IDLE_STOP]
            stopped = [self._views.pop(k) for k in idle]
        for view in stopped:
            view.stop()

    def stop_all(self) -> None:
        with self._lock:
            views, self._views = list(self._views.values()), {}
        for view in views:
            view.stop()


__all__ = ["RevisionView", "RevisionViews"]
