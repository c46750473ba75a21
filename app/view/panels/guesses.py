"""Octree guesses for one pair: both scans' occupied cubes, ranked candidates, ICP from a chosen one."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.editing import editor_for
from app.view import display
from app.view.controls import NO_CHOICE
from app.view.panels.host import ViewerHost
from slam6d.geometry import rotation_to_quaternion

_TOP = 10


class GuessPanel:
    def __init__(self, viewer: ViewerHost) -> None:
        self.viewer = viewer
        self.editor = editor_for(viewer.workbench)
        self.session_id = viewer.session_id
        self.summary: dict[str, Any] | None = None
        self.drawn: list[Any] = []
        gui = viewer.server.gui
        with gui.add_folder("Octree guess", expand_by_default=False):
            self.data = gui.add_number("Data scan (model = previous)", 1, min=1, step=1)
            self.level = gui.add_slider("Search level (0 = coarsest)", 0, 3, 1, 3)
            self.search = gui.add_button("Search candidates")
            self.table = gui.add_markdown("")
            self.choice = gui.add_dropdown("Candidate", [NO_CHOICE])
            self.apply = gui.add_button("Run ICP from candidate", disabled=True)
            self.show = gui.add_checkbox("Show cubes and candidates", True)
        run = viewer.run_safely
        self.search.on_click(lambda _: run(self._search))
        self.level.on_update(lambda _: run(self._search) if self.summary is not None else None)
        self.apply.on_click(lambda e: run(lambda: self._apply(e)))
        self.show.on_update(lambda _: self._set_visible(bool(self.show.value)))

    def _search(self) -> None:
        self.table.content = "Searching…"
        data = int(self.data.value)
        summary = self.editor.guesses.summary(self.session_id, data, None, int(self.level.value), _TOP)
        self.summary = summary
        self.level.max = len(summary["levels"]) - 1
        rows = [
            f"| {c['rank']} | {c['score']} | {c['fraction']:.0%} | "
            + " ".join(f"{v:+.2f}" for v in c["offsets"][:3])
            + " | "
            + " ".join(f"{np.degrees(v):+.1f}" for v in c["offsets"][3:])
            + f" | {'★' if c['winner'] else ''} |"
            for c in summary["candidates"]
        ]
        self.table.content = (
            f"Scan {summary['data']} onto {summary['model']} · cubes {summary['cube_size']:.2f} m · "
            f"{summary['model_cubes']} / {summary['data_cubes']} occupied · {summary['evaluated']} candidates\n\n"
            "| rank | score | hit | dx dy dz (m) | roll pitch yaw (°) | winner |\n|---|---|---|---|---|---|\n"
            + "\n".join(rows)
        )
        self.choice.options = [f"{c['rank']}: score {c['score']}" for c in summary["candidates"]]
        self.apply.disabled = False
        self._draw()

    def _draw(self) -> None:
        viewer = self.viewer
        summary = self.summary
        assert summary is not None
        for handle in self.drawn:
            handle.remove()
        self.drawn = []
        size = float(summary["cube_size"])
        poses = viewer.state.session.poses()
        add = viewer.server.scene
        for name, scan, colour in (
            ("model", summary["model"], display.MODEL_SCANS),
            ("data", summary["data"], display.DATA_SCAN),
        ):
            centres = self.editor.guesses.occupied_cubes(self.session_id, scan, size).astype(np.float32)
            pose = poses[scan]
            self.drawn.append(
                add.add_point_cloud(
                    f"/guess/{name}_cubes",
                    centres,
                    colors=colour,
                    point_size=size * 0.9,
                    point_shape="square",
                    precision="float32",
                    position=pose[:3, 3],
                    wxyz=rotation_to_quaternion(pose[:3, :3]),
                )
            )
        scores = np.array([c["score"] for c in summary["candidates"]], dtype=np.float64)
        colours = display.ramp(scores, float(scores.min()), float(scores.max()))
        for c, colour in zip(summary["candidates"], colours, strict=True):
            pose = np.asarray(c["pose"])
            self.drawn.append(
                add.add_frame(
                    f"/guess/candidate_{c['rank']}",
                    axes_length=1.2 if c["winner"] else 0.6,
                    axes_radius=0.04 if c["winner"] else 0.015,
                    origin_radius=0.12 if c["winner"] else 0.06,
                    origin_color=display.rgb(colour),
                    position=pose[:3, 3],
                    wxyz=rotation_to_quaternion(pose[:3, :3]),
                )
            )
        self._set_visible(bool(self.show.value))

    def _set_visible(self, visible: bool) -> None:
        for handle in self.drawn:
            handle.visible = visible

    def _apply(self, event: Any) -> None:
        if self.summary is None or self.choice.value == NO_CHOICE:
            raise ValueError("search and choose a candidate first")
        rank = int(self.choice.value.split(":")[0])
        s = self.summary
        out = self.editor.guesses.apply(
            self.session_id, s["data"], s["model"], rank, self.viewer.author(event), s["level"]
        )
        self.table.content += f"\n\nICP from candidate {rank}: fitness {out['fitness']:.2f}, RMS {out['rms']:.3f} m"
        self.viewer.warn(out["warning"] or "")

    def refresh(self) -> None:
        count = len(self.viewer.workbench.current_poses(self.session_id))
        self.data.max = max(count - 1, 1)
        if self.summary is not None:  # the poses changed: the shown search is stale
            self.summary = None
            self.apply.disabled = True
            self.choice.options = [NO_CHOICE]
            self.table.content = "The poses changed; search again."
            for handle in self.drawn:
                handle.remove()
            self.drawn = []
