"""Loop closing and relaxation of a session as background jobs: error diffusion, then a global solve.

Both refuse up front what cannot work (no loop to close; a graph whose scans are not all tied to a
fixed scan, as :class:`~slam6d.errors.RelaxationError` naming the loose scans), so a job only
starts when it can finish. The relaxation methods are the engine's, under the engine's names and
with the same default as ``slam6d run`` (``lum``), so a session relaxes the same from the browser and
from ``slam6d relax``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from app.editing.context import EditContext
from app.jobs import Cancel, Progress, Work
from app.workbench import EditError
from slam6d.loops import LoopHypothesis
from slam6d.pipeline import holds_inclinometer
from slam6d.posegraph import check_connected
from slam6d.relaxation_methods import RELAXATION_METHODS
from slam6d.residuals import displacements
from slam6d.session_relaxation import close_revision_loops, relax_revision, revision_tilt_prior, session_readings


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
            start = context.workbench.head(session_id)  # the revision this job works from
            before = list(start.poses)
            scans = context.workbench.state(session_id).sequence().scans
            keep_tilt = holds_inclinometer(context.config(session_id), [s.has_pose for s in scans])
            hypotheses = [LoopHypothesis(e["i"], e["j"], 0.0, 0.0, transform=np.asarray(e["transform"])) for e in loops]
            poses = close_revision_loops(
                before, hypotheses, keep_tilt, cancel, lambda done, total: progress("closing loops", done, total)
            )
            params = {
                "loops": [[e["i"], e["j"]] for e in loops],
                "tilt_kept": keep_tilt,
                "displacement": displacements(before, poses),
            }
            return context.commit_checked(session_id, poses, author, "close_loops", params, base=start.number)

        return work

    def check_relaxable(self, session_id: str, method: str, fixed: Sequence[int]) -> None:
        """Refuse up front what cannot run: an unknown method, no fixed scan, and for ``graph`` a graph
        whose scans are not all tied to a fixed one (RelaxationError naming the loose scans)."""
        if method not in RELAXATION_METHODS:
            raise EditError(f"unknown relaxation '{method}'; known: {', '.join(RELAXATION_METHODS)}", 422)
        count = self.context.check_scan(session_id, *fixed)
        if not fixed:
            raise EditError("no fixed scan: relaxation needs at least one scan held in place (usually scan 0)")
        if method == "graph":
            check_connected(count, [(e["i"], e["j"]) for e in self.context.edges(session_id)], fixed)

    def relax_job(self, session_id: str, author: str, method: str = "lum", fixed: Sequence[int] = (0,)) -> Work:
        """The engine's relaxation of a session's revision (:func:`slam6d.session_relaxation.relax_revision`)
        with the session's settings, as ``slam6d relax SESSION --method METHOD`` runs it: ``graph`` over
        the session's graph, and the odometry's tilt held where ``[engine] tilt_noise_deg`` declares an
        inclinometer (:func:`slam6d.session_relaxation.revision_tilt_prior`)."""
        self.check_relaxable(session_id, method, fixed)
        context = self.context
        config = context.config(session_id)

        def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
            models = context.models(session_id)
            revision = context.workbench.head(session_id)  # the revision this job works from
            poses = list(revision.poses)
            scans = context.workbench.state(session_id).sequence().scans
            tilt = revision_tilt_prior(
                config,
                method,
                lambda: session_readings(context.session(session_id), [s.has_pose for s in scans]),
                models,
            )
            rounds = config.relax.max_rounds
            result = relax_revision(
                method,
                models,
                revision,
                fixed,
                config,
                tilt,
                progress=lambda done, _residual, _moved: progress(f"{method}: rounds", done, rounds),
                cancel=cancel,
                edge_progress=lambda done, total: progress(f"{method}: matching edges", done, total),
                scheduler=context.workbench.scheduler(),
            )
            # held scans are no part of the change: someone may move them meanwhile without a conflict
            relaxed = [poses[k] if k in fixed else pose for k, pose in enumerate(result.poses)]
            params = {
                "method": method,
                "fixed": list(fixed),
                "rounds": result.iterations,
                "tilt_noise_deg": None if tilt is None else tilt.noise_deg,
                "residual_plane": [result.residual_before, result.residual_after],
                "displacement": displacements(poses, relaxed),
            }
            return context.commit_checked(session_id, relaxed, author, f"relax_{method}", params, base=revision.number)

        return work
