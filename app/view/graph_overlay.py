"""The pose graph drawn over the map: the trajectory and the loop edges, each coloured by its residual.

The residuals are the editor's per-edge summary (the numbers the "residuals jumped" guardrail
compares), computed in the background for the poses shown; until they are in, edges are grey.

They are computed against bounded copies of the scans, never the full ones: the first
:data:`RESIDUAL_SAMPLE` points of each scan's levels of detail (an even sample of it,
:mod:`slam6d.scan_levels`), reduced as the engine reduces scans. A 1,000-scan campus of 100M points
would otherwise be read in full (~3 GB resident) just to colour its edges; the sample is ~0.2 GB,
and the point-to-plane residual the colours show depends on the surfaces, not on the point spacing.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from app.view import display
from app.view.core import ShownScans, ViewContext
from slam6d.relax import ScanModels
from slam6d.scan_levels import ScanLevels

RESIDUAL_SAMPLE = 8192  # points per scan the edge residuals are computed from (a prefix of its levels)


class GraphOverlay:
    def __init__(
        self,
        view: ViewContext,
        scans: ShownScans,
        icp_max_distance: float,
        levels: Callable[[], ScanLevels | None],
    ) -> None:
        self.view = view
        self.scans = scans
        self.levels = levels  # the scans' levels of detail, once the view has loaded them
        self.models: ScanModels | None = None  # the scans' bounded copies the residuals are computed against
        self.edge_residuals: dict[tuple[int, int], float] = {}
        self.edge_residual_version = -1  # the pose_version edge_residuals were computed for
        self.edge_nodes: list[Any] = []  # the line nodes drawn, one per edge colour
        self.edge_colours: dict[str, np.ndarray] = {}  # per kind ("/graph/trajectory", "/graph/loops"), per edge
        # red from a quarter of the ICP pairing distance: an edge's point-to-plane residual (upper
        # quartile) sits near the range noise when its scans agree and reaches centimetres at
        # odometry-level errors
        self.edge_scale = icp_max_distance / 4  # metres: the residual drawn in full red
        self.edges_wanted = threading.Event()
        self.edges_worker: threading.Thread | None = None

    def draw(self) -> None:
        """Trajectory (sequential edges) and loop edges, each coloured by its point-to-plane residual.

        The residuals are the editor's per-edge summary (the numbers the "residuals jumped" guardrail
        compares), computed in the background for the poses shown; until they are in, edges are grey.
        """
        view, poses = self.view, self.scans.poses
        with view.lock:
            if not poses:
                return
            origin = poses[0][:3, 3]
            edges = [(e["i"], e["j"], e["kind"]) for e in view.editor.edges.listed(view.session_id)]
            edges = [e for e in edges if e[0] < len(poses) and e[1] < len(poses)]
            known = self.edge_residuals if self.edge_residual_version == self.scans.pose_version else None
            for node in self.edge_nodes:
                node.remove()
            drawn: list[Any] = []
            for name, sequential, thickness, toggle in (
                ("/graph/trajectory", True, 3.0, view.controls.show_trajectory),
                ("/graph/loops", False, 4.0, view.controls.show_edges),
            ):
                chosen = [(i, j) for i, j, kind in edges if (kind == "sequential") == sequential]
                if known is None:
                    colours = np.full((len(chosen), 3), 150, np.uint8)
                else:
                    residuals = [known.get((i, j), np.nan) for i, j in chosen]
                    colours = display.edge_colours(residuals, self.edge_scale)[:, 0]
                self.edge_colours[name] = colours
                segments = display.segments(chosen, poses)
                # one node per colour: viser's line segments take one colour per node reliably (its
                # per-vertex uint8 colours reach the browser's line material unnormalised, as white)
                shades, which = np.unique(colours, axis=0, return_inverse=True) if chosen else (colours, [])
                for b, shade in enumerate(shades):
                    drawn.append(
                        view.server.scene.add_line_segments(
                            f"{name}/{b}",
                            segments[np.asarray(which).reshape(-1) == b],
                            colors=display.rgb(shade),
                            thickness=thickness,
                            thickness_units="screen",
                            position=origin,
                            visible=bool(toggle.value),
                        )
                    )
            self.edge_nodes = drawn
            if known is None:
                self._edge_residuals_later()
            self._edge_legend(known)

    def _edge_residuals_later(self) -> None:
        """Compute the edges' residuals for the shown poses in the background, then recolour them.

        The first call reads and reduces the scans' samples (:meth:`sampled_models`; seconds for a
        large session, paid once), so it never holds up the map. Requests while one runs coalesce.
        """
        self.edges_wanted.set()
        if self.edges_worker is not None and self.edges_worker.is_alive():
            return

        view, scans = self.view, self.scans

        def work() -> None:
            view.ready.wait()  # after the full map is sent: the first look at a session comes first
            while self.edges_wanted.is_set() and not view.stopped:
                self.edges_wanted.clear()
                with view.lock:
                    version, poses = scans.pose_version, [p.copy() for p in scans.poses]
                try:
                    summary = view.editor.context.residuals(view.session_id, poses, models=self.sampled_models())
                    with view.lock:
                        if view.stopped:
                            return
                        if version != scans.pose_version:
                            continue  # moved meanwhile: the next request (or a redraw) computes them
                        self.edge_residuals = {(int(e["i"]), int(e["j"])): float(e["plane"]) for e in summary.edges}
                        self.edge_residual_version = version
                        self.draw()
                except Exception as exc:
                    if not view.stopped:
                        view.controls.edge_legend.content = f"Edge residuals unavailable: {exc}"
                    return

        self.edges_worker = threading.Thread(target=work, name=f"edge-residuals-{view.session_id}", daemon=True)
        self.edges_worker.start()

    def sampled_models(self) -> ScanModels:
        """The scans' first :data:`RESIDUAL_SAMPLE` points from their levels of detail, reduced as the
        engine reduces scans; read once per view, from the same levels the view shows."""
        if self.models is None:
            levels = self.levels()
            if levels is None:
                raise RuntimeError("the scans' levels of detail are not loaded")
            samples = [s.astype(np.float64) for s in levels.samples([RESIDUAL_SAMPLE] * len(levels))]
            self.models = self.view.editor.context.reduce(self.view.session_id, samples)
        return self.models

    def _edge_legend(self, known: dict[tuple[int, int], float] | None) -> None:
        low, high = (f"rgb{tuple(int(c) for c in rgb[0])}" for rgb in display.edge_colours([0, 1], 1.0))
        scale = (
            f"Edges by point-to-plane residual (upper quartile): <span style='color:{low}'>■</span> 0 m → "
            f"<span style='color:{high}'>■</span> ≥ {self.edge_scale:.2f} m or no overlap"
        )
        if known is None:
            self.view.controls.edge_legend.content = f"{scale} · computing…"
            return
        finite = {edge: rms for edge, rms in known.items() if np.isfinite(rms)}
        worst = max(known, key=lambda e: np.inf if not np.isfinite(known[e]) else known[e], default=None)
        detail = ""
        if worst is not None:
            value = known[worst]
            detail = f" · worst {worst[0]}–{worst[1]}: " + (f"{value:.3f} m" if np.isfinite(value) else "no overlap")
        if finite:
            detail += f" · median {np.median(list(finite.values())):.3f} m"
        self.view.controls.edge_legend.content = scale + detail
