"""Loop closing and relaxation of a session as background jobs: error diffusion, then a global solve.

Both refuse up front what cannot work (no loop to close; a graph whose scans are not all tied to a
fixed scan, as :class:`~slam6d.errors.RelaxationError` naming the loose scans), so a job only
starts when it can finish. The relaxation methods are the engine's, under the engine's names.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from app.editing.context import EditContext
from app.jobs import Cancel, Progress, Work
from app.workbench import EditError
from slam6d.errors import Cancelled
from slam6d.graph_relaxation import GraphEdge, graph_relaxation
from slam6d.loops import LoopHypothesis, diffuse_loop_correction, loop_correction
from slam6d.posegraph import check_connected
from slam6d.residuals import displacements
from slam6d.simultaneous import simultaneous_matching

RELAX_METHODS = ("lum", "simultaneous")


class Relaxation:
    def __init__(self, context: EditContext) -> None:
        self.context = context

    def close_loops_job(self, session_id: str, author: str) -> Work:
        """Error diffusion over every loop edge that carries an ICP transform, oldest loop end first."""
        context = self.context
        edges = context.edges(session_id)
        loops = [e for e in edges if e["kind"] != "sequential" and e.get("transform") is not None]
        if not loops:
            raise EditError("there is no accepted loop or manual edge with an ICP transform to close")
        loops.sort(key=lambda e: (e["j"], e["i"]))

        def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
            poses = context.poses(session_id)
            before = [p.copy() for p in poses]
            for n, edge in enumerate(loops):
                if cancel():
                    raise Cancelled("loop closing cancelled")
                hyp = LoopHypothesis(edge["i"], edge["j"], 0.0, 0.0, transform=np.asarray(edge["transform"]))
                poses = diffuse_loop_correction(poses, hyp.i, hyp.j, loop_correction(poses, hyp))
                progress("closing loops", n + 1, len(loops))
            params = {"loops": [[e["i"], e["j"]] for e in loops], "displacement": displacements(before, poses)}
            return context.commit_checked(session_id, poses, author, "close_loops", params)

        return work

    def check_relaxable(self, session_id: str, fixed: Sequence[int]) -> list[dict[str, Any]]:
        """The graph's edges if relaxation can run; else RelaxationError / EditError with the reason."""
        count = self.context.check_scan(session_id, *fixed)
        if not fixed:
            raise EditError("no fixed scan: relaxation needs at least one scan held in place (usually scan 0)")
        edges = self.context.edges(session_id)
        check_connected(count, [(e["i"], e["j"]) for e in edges], fixed)
        return edges

    def relax_job(self, session_id: str, author: str, method: str = "lum", fixed: Sequence[int] = (0,)) -> Work:
        """Simultaneous matching (the engine's, over overlapping scans) or LUM over this session's graph."""
        if method not in RELAX_METHODS:
            raise EditError(f"unknown relaxation '{method}'; known: {', '.join(RELAX_METHODS)}", 422)
        context = self.context
        edges = self.check_relaxable(session_id, fixed)
        relax_config = context.config(session_id).relax

        def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
            models = context.models(session_id)
            poses = context.poses(session_id)
            if method == "simultaneous":
                result = simultaneous_matching(
                    models,
                    poses,
                    fixed=fixed,
                    config=relax_config,
                    progress=lambda it, _r, _m: progress("simultaneous matching", it, it + 1),
                    cancel=cancel,
                )
                info: dict[str, Any] = {"iterations": result.iterations}
            else:
                graph = [GraphEdge(e["i"], e["j"], e.get("transform")) for e in edges]
                result = graph_relaxation(
                    models,
                    poses,
                    graph,
                    fixed,
                    relax_config,
                    cancel=cancel,
                    edge_progress=lambda done, total: progress("LUM: matching edges", done, total),
                )
                info = {"rounds": result.iterations, "chi2": [result.chi2_before, result.chi2_after]}
            relaxed = result.poses
            params = {"method": method, "fixed": list(fixed), **info, "displacement": displacements(poses, relaxed)}
            return context.commit_checked(session_id, relaxed, author, f"relax_{method}", params)

        return work
