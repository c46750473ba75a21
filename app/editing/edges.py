"""Correcting the graph and the poses by hand: add an ICP-refined edge, delete an edge, move a scan."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from app.editing.context import EditContext
from app.workbench import EditError
from slam6d.errors import RegistrationError
from slam6d.geometry import Matrix, invert
from slam6d.icp import icp
from slam6d.loops import LoopHypothesis, verify
from slam6d.session_graph import GraphDocument, edge_key, with_loop, without_loop
from slam6d.simultaneous import UnionIndex


class GraphEdits:
    def __init__(self, context: EditContext) -> None:
        self.context = context

    def listed(self, session_id: str) -> list[dict[str, Any]]:
        """The current pose graph's edges; ``k`` is what :meth:`delete` takes."""
        return self.context.edges(session_id)

    def add(self, session_id: str, i: int, j: int, author: str, force: bool = False) -> dict[str, Any]:
        """A loop edge between two scans, refined by ICP from their current relative pose."""
        context = self.context
        context.check_scan(session_id, i, j)
        if i == j:
            raise EditError("an edge needs two different scans", 422)
        i, j = edge_key(i, j)
        poses = context.poses(session_id)
        models = context.models(session_id)
        hyp = LoopHypothesis(i, j, float(np.linalg.norm(poses[i][:3, 3] - poses[j][:3, 3])), 0.0)
        hyp.transform = invert(poses[i]) @ poses[j]
        verdict = verify(hyp, models.index(i), models.points[j], models.config, context.config(session_id).loop)
        if not verdict.accepted and not force:
            raise EditError(f"scans {i} and {j} do not match ({verdict.reason}); add it anyway with force", 422)
        edge = {
            "i": i,
            "j": j,
            "kind": "manual",
            "fitness": float(verdict.fitness),
            "rms": float(verdict.rms),
            "transform": np.asarray(verdict.transform).tolist(),
        }
        parameters = {"i": i, "j": j, "fitness": edge["fitness"], "rms": edge["rms"], "forced": bool(force)}
        revision = context.commit_graph(
            session_id, lambda graph: with_loop(graph, edge), author, "add_edge", parameters
        )
        return {"revision": revision, "edge": edge, "warning": None if verdict.accepted else verdict.reason}

    def delete(self, session_id: str, k: int, author: str) -> dict[str, Any]:
        """Edge ``k`` of :meth:`listed` leaves the graph (a sequential edge is recorded as removed)."""
        context = self.context
        graph = context.session(session_id).graph()
        listed = context.edges(session_id, graph)
        if not 0 <= k < len(listed):
            raise EditError(f"no edge {k}; there are {len(listed)}", 404)
        edge = listed[k]

        def remove(head: GraphDocument) -> GraphDocument:  # the edge by its scans: k may have shifted meanwhile
            if edge["kind"] == "sequential":
                return {**head, "removed": [*head.get("removed", []), edge_key(edge["i"], edge["j"])]}
            return without_loop(head, edge["i"], edge["j"])

        params = {"edge": k, "i": edge["i"], "j": edge["j"], "kind": edge["kind"]}
        revision = context.commit_graph(session_id, remove, author, "delete_edge", params)
        return {"revision": revision, "deleted": {key: edge[key] for key in ("i", "j", "kind")}}

    def move_scan(
        self, session_id: str, k: int, pose: Matrix, author: str, refine: bool = False, carry: Sequence[int] = ()
    ) -> dict[str, Any]:
        """Place scan k (a drag of the gizmo); with ``refine`` ICP continues from there against its neighbours.

        ``carry`` scans move rigidly with scan k (its connected component, when the operator brings a
        piece that sits far off next to the rest to bridge them): they keep their poses relative to
        scan k, and ICP matches scan k only against graph neighbours outside them, since the carried
        ones move along and cannot tell where the piece belongs."""
        context = self.context
        context.check_scan(session_id, k, *carry)
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise EditError("pose must be a finite 4x4 matrix", 422)
        carried = sorted(set(carry) - {k})
        head = context.workbench.head(session_id)
        poses = list(head.poses)
        params: dict[str, Any] = {"scan": k, "pose": pose, "refine": refine}
        if carried:
            params["carry"] = carried
        if refine:
            neighbours = sorted(
                {e["j"] if e["i"] == k else e["i"] for e in context.edges(session_id) if k in (e["i"], e["j"])}
                - set(carried)
            )
            if not neighbours:
                moved_along = " outside the scans carried along" if carried else ""
                raise EditError(f"scan {k} has no edges{moved_along} to refine against")
            models = context.models(session_id)
            try:
                result = icp(UnionIndex(models, neighbours, poses), models.points[k], pose, models.config)
            except RegistrationError as exc:
                raise EditError(f"ICP from the new place failed: {exc}", 422) from None
            pose = result.transform
            params.update(neighbours=neighbours, fitness=result.fitness, rms=result.rms)
        along = pose @ invert(poses[k])  # the move scan k makes, applied to the carried scans too
        for c in carried:
            poses[c] = along @ poses[c]
        poses[k] = pose
        kind = "icp_move" if refine else "manual_move"
        return context.commit_checked(session_id, poses, author, kind, params, base=head.number)
