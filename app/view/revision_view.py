"""Private 3D views: a revision drawn read-only in a scene of each browser's own.

The session's live 3D view (:mod:`app.view.session_view`) is one scene shared by everyone on it:
its colours, picks and playback are the editors' common workspace. Two kinds of browser need a
scene of their own instead, and both connect to a :class:`RevisionView` - a viser server of its
own drawing the scans (at the levels of detail of the live view's first look) at one revision's
poses with that revision's pose-graph edges:

* a permalink to an **older revision** must show that revision without moving anyone else's map
  (``follows_head`` false: the view stays at its revision);
* a browser whose **colour mode** is its own - a viewer or reviewer opening a link with another
  colour mode than the live view's, or choosing one - sees the **head** in its own colours
  (``follows_head`` true: the view moves to every new revision as the live view does).

Everything is added to each browser's *own* scene (``client.scene``), so each browser on a view
has its own colour mode and selection marker (:mod:`app.view.selection_marker`); a click in the
scene picks the scan under it for that browser alone (the page puts it in its address).

It is read-only by construction: it has no edit controls, and its websocket is forwarded with a
viewer's rights (:mod:`app.view_roles`), so nothing a browser sends reaches it but its camera and
its clicks. Views nobody has looked at for :data:`IDLE_STOP` seconds are stopped; at most
:data:`MAX_VIEWS` (older revisions and heads together) are open per server.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from app.errors import EditError
from app.permalink import Selection
from app.view import display
from app.view.detail_levels import choose_levels
from app.view.picking import pick_scan
from app.view.presence import presence_of
from app.view.selection_marker import marker_of
from app.workbench import SessionState, Workbench
from slam6d.geometry import Matrix, rotation_to_quaternion
from slam6d.scan_levels import session_levels
from slam6d.session_graph import graph_edge_list

IDLE_STOP = 120.0  # s without a browser before a private view is stopped
# private views open at once on one server, older revisions and heads in a browser's own colours
# together: each holds a coarse copy of its session's map (display.COARSE_BUDGET points)
MAX_VIEWS = 8
EDGE_COLOURS = {"sequential": (150, 150, 150), "loop": (255, 138, 31), "manual": (80, 200, 255)}


@dataclass
class BrowserScene:
    """One browser's own scene of the revision: its scan nodes, edge nodes and colour mode."""

    client: Any  # viser ClientHandle
    nodes: list[Any] = field(default_factory=list)
    edges: list[Any] = field(default_factory=list)
    colour: str = "scan"


class RevisionView:
    """A session's revision drawn read-only for each browser that connects: ``revision`` (an older one,
    kept) or, with ``revision`` None, the head, followed as it moves (:meth:`follow_head`)."""

    def __init__(self, state: SessionState, revision: int | None) -> None:
        self.state = state
        self.session_id = state.session.id
        self.follows_head = revision is None
        self.lock = threading.RLock()
        self.browsers: dict[int, BrowserScene] = {}
        self.last_seen = time.monotonic()
        self.local: list[np.ndarray] = []  # display points per scan, scanner frame
        self.bounds: list[tuple[np.ndarray, np.ndarray]] = []  # their (low, high) corners
        if revision is None:
            state.sequence()  # the head's first revision is written when the session's scans are first read
        self._read(state.session.revision if revision is None else revision)
        title = "the current revision in your own colours" if self.follows_head else f"revision {revision}"
        self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False, label=title)
        self.port = self.server.get_port()
        self.server.scene.set_up_direction("+z")
        self.server.scene.configure_default_lights(cast_shadow=False)
        self.server.gui.configure_theme(dark_mode=True, control_width="large")
        self.status = self.server.gui.add_markdown("")
        self._show_status()
        positions = np.array([p[:3, 3] for p in self.poses]) if self.poses else np.zeros((1, 3))
        lo, hi = positions.min(axis=0), positions.max(axis=0)
        size = max(float(np.linalg.norm(hi - lo)), 20.0)
        self.server.initial_camera.look_at = (lo + hi) / 2
        self.server.initial_camera.position = (lo + hi) / 2 + np.array([-0.4, -0.6, 0.7]) * size
        presence_of(self)  # who is who: before any browser connects
        self.server.on_client_connect(self._connected)
        self.server.on_client_disconnect(self._disconnected)
        self.server.scene.on_click()(self._clicked)

    def _read(self, revision: int) -> None:
        """Take revision ``revision``'s poses and edges, and the scans' display points if their number changed."""
        state = self.state
        found = state.session.get_revision(revision)
        poses: list[Matrix] = [np.asarray(p, dtype=np.float64) for p in found.poses]
        edges = [(int(e["i"]), int(e["j"]), str(e["kind"])) for e in graph_edge_list(len(poses), found.graph)]
        with self.lock:
            if len(poses) != len(self.local):
                # the live view's first look: every scan at the levels of detail that fit the coarse budget,
                # read as prefixes of the session's level store (built by the live view, or here if absent)
                levels = session_levels(state.session, lambda: state.sequence().scans)
                chosen = choose_levels(levels.level_points, np.ones(len(levels)), display.COARSE_BUDGET)
                self.local = [levels.points(k, level) for k, level in enumerate(chosen)]
                self.bounds = [
                    (c.min(axis=0), c.max(axis=0)) if len(c) else (np.zeros(3), np.zeros(3)) for c in self.local
                ]
            self.revision = revision
            self.poses = poses
            self.edges = edges
            self._residuals: list[np.ndarray] | None = None
            self._components = _components(len(poses), [(i, j) for i, j, _ in edges])
            self._height_range = display.height_range(self.local, poses)

    def _show_status(self) -> None:
        name = self.state.session.name
        points = f"{len(self.local)} scans · {sum(len(p) for p in self.local):,} points shown"
        if self.follows_head:
            self.status.content = (
                f"**{name} · revision {self.revision}** · {points} · in your own colours, following every "
                "new revision; edits are made in the shared 3D view (an editor's)."
            )
        else:
            self.status.content = (
                f"**{name} · revision {self.revision}** (read-only) · {points}: the map as it was then. "
                "The page's banner leads to the current revision."
            )

    # -------------------------------------------------------------- each browser's scene

    def _connected(self, client: Any) -> None:
        browser = BrowserScene(client)
        with self.lock:
            self.browsers[client.client_id] = browser
            self.last_seen = time.monotonic()
            self._draw(browser)

    def _draw(self, browser: BrowserScene) -> None:
        """Add every scan and the pose-graph edges to the browser's own scene (replacing what was there)."""
        client = browser.client
        with client.atomic():
            for gone in browser.nodes[len(self.local) :]:  # scans the revision no longer has
                gone.remove()
            browser.nodes = [
                client.scene.add_point_cloud(
                    f"/scans/{k}",
                    points=points,
                    colors=self._colours(k, browser.colour),
                    point_size=0.03,
                    point_shading="flat",
                    precision=display.precision_for(points),
                    position=self.poses[k][:3, 3],
                    wxyz=rotation_to_quaternion(self.poses[k][:3, :3]),
                )
                for k, points in enumerate(self.local)
            ]
            self._draw_edges(browser)

    def _draw_edges(self, browser: BrowserScene) -> None:
        for handle in browser.edges:
            handle.remove()
        browser.edges = []
        for kind, colour in EDGE_COLOURS.items():
            pairs = [(i, j) for i, j, k in self.edges if k == kind]
            if pairs:
                browser.edges.append(
                    browser.client.scene.add_line_segments(
                        f"/graph/{kind}",
                        display.segments(pairs, self.poses),
                        colors=colour,
                        thickness=3.0 if kind == "sequential" else 4.0,
                        thickness_units="screen",
                        position=self.poses[0][:3, 3],
                    )
                )

    def _disconnected(self, client: Any) -> None:
        with self.lock:
            self.browsers.pop(client.client_id, None)
            self.last_seen = time.monotonic()

    def _clicked(self, event: Any) -> None:
        """A click in a browser's scene picks the scan under it, for that browser alone (its page puts it
        in the address and marks it)."""
        with self.lock:
            k = pick_scan(self.local, self.poses, event.ray_origin, event.ray_direction)
        if k is not None:
            marker_of(event.client).picked(Selection("scan", k))

    def follow_head(self) -> None:
        """The session's head moved: a view following it draws the new poses and edges in every browser's
        scene, recoloured where the colour mode depends on them. A view of an older revision stays."""
        head = self.state.session.revision
        if not self.follows_head or head == self.revision:
            return
        with self.lock:
            count = len(self.local)
            self._read(head)
            self._show_status()
            for browser in list(self.browsers.values()):
                if len(self.local) != count:  # scans came or went: everything anew
                    self._draw(browser)
                    continue
                with browser.client.atomic():
                    for k, node in enumerate(browser.nodes):
                        node.position = self.poses[k][:3, 3]
                        node.wxyz = rotation_to_quaternion(self.poses[k][:3, :3])
                    self._draw_edges(browser)
                if browser.colour != "scan":  # height, residual and component follow the poses and edges
                    self._paint(browser)

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
            raise EditError("that browser has left this view", 404)
        return found

    def set_colour(self, client_id: int, mode: str) -> None:
        """Colour one browser's scans by ``mode``; nobody else's view changes."""
        browser = self.browser(client_id)
        with self.lock:
            browser.colour = mode
            self._paint(browser)

    def _paint(self, browser: BrowserScene) -> None:
        with self.lock:
            colours = [np.asarray(self._colours(k, browser.colour), np.uint8) for k in range(len(self.local))]
        with browser.client.atomic():
            for node, colour in zip(browser.nodes, colours, strict=True):
                node.colors = colour

    def as_dict(self) -> dict[str, Any]:
        """What this view draws: its revision, whether it follows the head, each scan's position there and
        each browser's colour mode (the page and tests read it)."""
        with self.lock:
            colours = {str(cid): b.colour for cid, b in self.browsers.items()}
            positions = [[float(v) for v in p[:3, 3]] for p in self.poses]
            return {
                "ready": True,
                "revision_shown": self.revision,
                "read_only": True,
                "follows_head": self.follows_head,
                "scans": len(self.poses),
                "points_shown": int(sum(len(p) for p in self.local)),
                "positions": positions,
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
    """The private views open on a server - older revisions, and heads in a browser's own colours (at most
    one per session, shared by all such browsers): started when a page first asks, stopped after nobody
    looks, at most :data:`MAX_VIEWS` at once."""

    def __init__(self, workbench: Workbench) -> None:
        self.workbench = workbench
        self._views: dict[tuple[str, int | None], RevisionView] = {}  # (session, revision; None: its head)
        self._lock = threading.Lock()
        workbench.on_revision(self._head_moved)

    def get(self, session_id: str, revision: int | None) -> RevisionView:
        """The view of ``revision`` of the session (None: its head, followed), started if none is open;
        :class:`EditError` 409 when :data:`MAX_VIEWS` are open already."""
        self._stop_idle()
        with self._lock:
            view = self._views.get((session_id, revision))
            if view is not None:
                view.last_seen = time.monotonic()
                return view
            if len(self._views) >= MAX_VIEWS:
                raise EditError(
                    f"{MAX_VIEWS} private 3D views (older revisions, or the current one in a browser's own "
                    f"colours) are open on this server already; one closes {IDLE_STOP / 60:.0f} minutes after "
                    "its last browser leaves - try again then",
                    409,
                )
            view = self._views[(session_id, revision)] = RevisionView(self.workbench.state(session_id), revision)
            return view

    def of_session(self, session_id: str) -> list[RevisionView]:
        with self._lock:
            return [v for (s, _), v in self._views.items() if s == session_id]

    def _head_moved(self, session_id: str) -> None:
        with self._lock:
            view = self._views.get((session_id, None))
        if view is not None:
            view.follow_head()

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
