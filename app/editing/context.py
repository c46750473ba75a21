"""What every edit of a session needs: its engine settings, its reduced scans, its edges, a checked commit.

Each edit (loops, edges, moves, relaxation, guesses) is one journal entry with author and
parameters; edits that move scans go through :meth:`EditContext.commit_checked`, which compares the
engine's residual summary before and after and reports a jump as a warning. Guardrails live here,
not in the GUI, so a button and a REST call are held to the same checks.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

from app.workbench import EditError, Workbench
from slam6d.engine_settings import pipeline_config
from slam6d.geometry import Matrix
from slam6d.graph_relaxation import graph_information
from slam6d.journal import Change
from slam6d.pipeline import PipelineConfig
from slam6d.relax import FloatArray, ScanModels
from slam6d.relaxation_methods import reduced_models
from slam6d.residuals import ResidualSummary, residual_jump, residual_summary
from slam6d.session import Session
from slam6d.session_graph import GraphDocument, graph_edge_list, graph_edges


class EditContext:
    """One workbench's sessions as edits see them; keeps each session's reduced scans (built once) for ICP."""

    def __init__(self, workbench: Workbench) -> None:
        self.workbench = workbench
        self._models: dict[str, tuple[int, ScanModels]] = {}
        self.lock = threading.Lock()
        workbench.on_release(self.forget)

    def forget(self, session_id: str) -> None:
        """Drop a session's reduced scans (its scans were released from memory; rebuilt on next use)."""
        with self.lock:
            self._models.pop(session_id, None)

    def session(self, session_id: str) -> Session:
        return self.workbench.state(session_id).session

    def config(self, session_id: str) -> PipelineConfig:
        """The session's ``[engine]`` settings, as ``slam6d run`` would read them."""
        return pipeline_config(self.session(session_id).config.engine)

    def models(self, session_id: str) -> ScanModels:
        """Each scan reduced as the engine's pipeline and ``slam6d relax`` reduce it, kd-trees built on first use."""
        sequence = self.workbench.state(session_id).sequence()
        with self.lock:
            cached = self._models.get(session_id)
            if cached is not None and cached[0] == id(sequence):
                return cached[1]
            models = self.reduce(session_id, [s.points for s in sequence.scans])
            self._models[session_id] = (id(sequence), models)
            return models

    def poses(self, session_id: str) -> list[Matrix]:
        return self.workbench.current_poses(session_id)

    def check_scan(self, session_id: str, *indices: int) -> int:
        """The session's scan count; EditError (404) naming the range when an index is outside it."""
        count = len(self.poses(session_id))
        for k in indices:
            if not 0 <= k < count:
                raise EditError(f"no scan {k}; the session has scans 0..{count - 1}", 404)
        return count

    def edges(self, session_id: str, graph: dict[str, Any] | None = None) -> list[dict[str, Any]]:
        """The edges of ``graph`` (default: the current revision's) as the user sees them."""
        count = len(self.poses(session_id))
        return graph_edge_list(count, self.session(session_id).graph() if graph is None else graph)

    def edge_information(self, session_id: str, poses: Sequence[Matrix], graph: dict[str, Any]) -> list[Matrix]:
        """Per edge of ``graph`` (in :func:`graph_edge_list`'s order), the information matrix of its relative
        pose at ``poses``, from the scans' overlap: what a g2o export states."""
        edges = graph_edges(len(poses), graph)
        return graph_information(self.models(session_id), poses, edges, self.config(session_id).relax)

    def residuals(
        self,
        session_id: str,
        poses: Sequence[Matrix] | None = None,
        graph: dict[str, Any] | None = None,
        models: ScanModels | None = None,
    ) -> ResidualSummary:
        """The engine's residual summary of the edges of ``graph`` at ``poses``; against ``models`` when
        given (e.g. the 3D view's bounded copies of the scans), else the session's reduced scans."""
        poses = self.poses(session_id) if poses is None else poses
        pairs = [(e["i"], e["j"]) for e in self.edges(session_id, graph)]
        return residual_summary(self.models(session_id) if models is None else models, poses, pairs)

    def reduce(self, session_id: str, points: Sequence[FloatArray]) -> ScanModels:
        """Models of ``points`` (one cloud per scan, its own frame) reduced as the session's engine reduces
        scans: :meth:`models` of the full scans, or of bounded samples of them (the 3D view's edge colours)."""
        config = self.config(session_id)
        return reduced_models(list(points), config.voxel_size, config.icp)

    def commit_checked(
        self,
        session_id: str,
        poses: Sequence[Matrix],
        author: str,
        kind: str,
        parameters: dict[str, Any],
        base: int,
    ) -> dict[str, Any]:
        """Commit poses computed from revision ``base`` with the residual summary before and after; a
        jump becomes ``warning``.

        Only the scans that differ from ``base`` are written, onto the head as it is then: an edit of
        other scans made meanwhile is kept; an edit of the same scans refuses this one (409 naming it).
        """
        before = self.residuals(session_id)
        after = self.residuals(session_id, poses)
        warning = residual_jump(before, after)
        params = {**parameters, "base": base, "residual_before": before.rms, "residual_after": after.rms}
        if warning:
            params["warning"] = warning
        revision = self.workbench.commit(session_id, list(poses), author, kind, params, base=base)
        return {
            "revision": revision,
            "residual_before": before.as_dict(),
            "residual_after": after.as_dict(),
            "warning": warning,
        }

    def commit_graph(
        self,
        session_id: str,
        change: Callable[[GraphDocument], GraphDocument],
        author: str,
        kind: str,
        parameters: dict[str, Any],
    ) -> int:
        """A new revision that changes only the graph: ``change`` runs on the head's graph as it is when
        written, so an edge someone else added a moment ago stays."""
        return self.workbench.apply(session_id, Change(graph=change), author, kind, parameters)
