"""Correcting by hand: add an ICP-refined edge between two scans, delete an edge, drag a scan with a gizmo."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.editing import editor_for
from app.permalink import Selection
from app.view.controls import NO_CHOICE
from app.view.panels.host import ViewerHost
from app.view.panels.paging import Pager
from app.view.selection_marker import marker_of
from slam6d.geometry import make_pose, quaternion_to_rotation, rotation_to_quaternion

PICKED_A = (255, 255, 255)
PICKED_B = (255, 60, 200)


class EdgesPanel:
    def __init__(self, viewer: ViewerHost) -> None:
        self.viewer = viewer
        self.editor = editor_for(viewer.workbench)
        self.session_id = viewer.session_id
        self.gizmo: Any = None
        gui = viewer.server.gui
        self.next_pick = "A"  # clicks in the view alternate: A, then B
        self.chosen: set[str] = set()  # "A", "B": drawn highlighted once someone picked or typed them
        self.edge_choices: dict[str, Selection] = {}  # the Edge dropdown's options -> the edges they name
        with gui.add_folder("Edit graph", expand_by_default=False):
            self.pick_status = gui.add_markdown("Click a scan in the view to pick scan A, then B.")
            self.scan_a = gui.add_number("Scan A", 0, min=0, step=1)
            self.scan_b = gui.add_number("Scan B", 1, min=0, step=1)
            self.force = gui.add_checkbox("Keep edge even if ICP disagrees", False)
            self.add = gui.add_button("Add edge A–B (ICP)")
            self.edge = gui.add_dropdown("Edge", [NO_CHOICE])
            self.edge_pages = Pager(gui, "Edges page", lambda: viewer.run_safely(self.refresh))
            self.delete = gui.add_button("Delete edge")
            self.drag = gui.add_checkbox("Drag scan A (gizmo)", False)
            # bridging: a component that sits far off comes along with its scan A (see the Components folder)
            self.carry = gui.add_checkbox("Carry A's component along", False)
            self.commit_move = gui.add_button("Keep dragged pose", disabled=True)
            self.icp_here = gui.add_button("ICP from here", disabled=True)
            self.result = gui.add_markdown("")
        run = viewer.run_safely
        viewer.server.scene.on_click()(lambda e: run(lambda: self._clicked(e)))
        self.scan_a.on_update(lambda e: run(lambda: self._typed("A", e)))
        self.scan_b.on_update(lambda e: run(lambda: self._typed("B", e)))
        self.add.on_click(lambda e: run(lambda: self._add(e)))
        self.delete.on_click(lambda e: run(lambda: self._delete(e)))
        self.edge.on_update(lambda e: run(lambda: self._edge_chosen(e)))
        self.drag.on_update(lambda _: run(self._toggle_gizmo))
        self.commit_move.on_click(lambda e: run(lambda: self._move(e, refine=False)))
        self.icp_here.on_click(lambda e: run(lambda: self._move(e, refine=True)))

    def _clicked(self, event: Any) -> None:
        k = self.viewer.picking.pick(event.ray_origin, event.ray_direction)
        if k is None:
            self.pick_status.content = f"No scan under the cursor; the next click still picks scan {self.next_pick}."
            return
        self.pick(k)
        if event.client is not None:  # the clicking browser's page selects it too
            marker_of(event.client).picked(Selection("scan", k))

    def _edge_chosen(self, event: Any) -> None:
        """An edge chosen in the dropdown by a person (not by a refresh) is that browser's selection too."""
        chosen = self.edge_choices.get(self.edge.value)
        if event.client is not None and chosen is not None:
            marker_of(event.client).picked(chosen)

    def pick(self, k: int) -> None:
        """Scan ``k`` becomes A or B (alternating), as if typed in, and is highlighted."""
        which, self.next_pick = self.next_pick, "B" if self.next_pick == "A" else "A"
        self.chosen.add(which)
        field = self.scan_a if which == "A" else self.scan_b
        field.value = k  # type: ignore[misc]
        self._highlight()
        name = self.viewer.state.sequence().scans[k].name
        self.pick_status.content = (
            f"Picked scan **{k}** ({name}) as **{which}** · A = {int(self.scan_a.value)}, "
            f"B = {int(self.scan_b.value)} · the next click picks {self.next_pick}"
        )

    def _typed(self, which: str, event: Any) -> None:
        if event.client is not None:  # typed by a person (picks set the fields from here, client None)
            self.chosen.add(which)
        self._highlight()

    def _highlight(self) -> None:
        selected = {int(self.scan_b.value): PICKED_B} if "B" in self.chosen else {}
        if "A" in self.chosen:
            selected[int(self.scan_a.value)] = PICKED_A  # A wins when both name one scan
        self.viewer.colouring.select(selected)

    def _add(self, event: Any) -> None:
        i, j = int(self.scan_a.value), int(self.scan_b.value)
        out = self.editor.edges.add(self.session_id, i, j, self.viewer.author(event), bool(self.force.value))
        edge = out["edge"]
        self.result.content = (
            f"edge {edge['i']}–{edge['j']} added (fitness {edge['fitness']:.2f}, RMS {edge['rms']:.3f} m), "
            f"revision {out['revision']}"
        )
        self.viewer.warn(out["warning"] or "")

    def _delete(self, event: Any) -> None:
        if self.edge.value == NO_CHOICE:
            raise ValueError("choose an edge first")
        k = int(self.edge.value.split(":")[0])
        out = self.editor.edges.delete(self.session_id, k, self.viewer.author(event))
        d = out["deleted"]
        self.result.content = f"{d['kind']} edge {d['i']}–{d['j']} deleted, revision {out['revision']}"

    def _toggle_gizmo(self) -> None:
        viewer = self.viewer
        if self.gizmo is not None:
            self.gizmo.remove()
            self.gizmo = None
        dragging = bool(self.drag.value)
        self.commit_move.disabled = self.icp_here.disabled = not dragging
        if not dragging:
            viewer.set_poses(viewer.state.session.poses())  # an unkept drag is dropped
            return
        k = int(self.scan_a.value)
        pose = viewer.scans.poses[k]
        self.gizmo = viewer.server.scene.add_transform_controls(
            "/edit/gizmo", scale=2.0, position=pose[:3, 3], wxyz=rotation_to_quaternion(pose[:3, :3])
        )

        @self.gizmo.on_update
        def _(_: Any) -> None:  # the scan (and what it carries) follows the gizmo (pose-only update)
            moved = self._gizmo_pose()
            shown = list(viewer.state.session.poses())  # a copy: the revision's own list stays as stored
            along = moved @ np.linalg.inv(shown[k])
            carried = self._carried(k)
            for c in carried:
                shown[c] = along @ shown[c]
            shown[k] = moved
            viewer.set_poses(shown, [k, *carried])

    def _carried(self, k: int) -> list[int]:
        """The other scans of scan k's connected component when *Carry A's component along* is on."""
        if not self.carry.value:
            return []
        piece = self.viewer.colouring.component_of.get(k)
        return sorted(s for s, c in self.viewer.colouring.component_of.items() if c == piece and s != k)

    def _gizmo_pose(self) -> np.ndarray:
        return make_pose(quaternion_to_rotation(np.asarray(self.gizmo.wxyz)), np.asarray(self.gizmo.position))

    def _move(self, event: Any, refine: bool) -> None:
        if self.gizmo is None:
            raise ValueError("turn on 'Drag scan A' first")
        k = int(self.scan_a.value)
        carried = self._carried(k)
        out = self.editor.edges.move_scan(
            self.session_id, k, self._gizmo_pose(), self.viewer.author(event), refine, carried
        )
        self.drag.value = False  # type: ignore[misc]
        along = f" with {len(carried)} scan(s) of its component" if carried else ""
        self.result.content = (
            f"scan {k}{along} {'matched from the dragged place' if refine else 'moved'}: residual RMS "
            f"{out['residual_before']['rms']:.3f} → {out['residual_after']['rms']:.3f} m, revision {out['revision']}"
        )
        self.viewer.warn(out["warning"] or "")

    def refresh(self) -> None:
        edges, _ = self.edge_pages.page(self.editor.edges.listed(self.session_id), "edges")
        self.edge_choices = {
            f"{e['k']}: {e['i']}–{e['j']} {e['kind']}": Selection.pair("edge", e["i"], e["j"]) for e in edges
        }
        options = list(self.edge_choices) or [NO_CHOICE]
        previous = self.edge.value
        self.edge.options = options
        self.edge.value = previous if previous in options else options[0]  # type: ignore[misc]
        count = len(self.viewer.workbench.current_poses(self.session_id))
        self.scan_a.max = self.scan_b.max = max(count - 1, 0)
