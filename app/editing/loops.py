"""Loop hypotheses to review: detect them from the current poses, list them, accept or reject one.

The review list is a journal entry of kind ``loop_hypotheses`` (written by detection and after a
registration run): finding loops changes nothing. Accepting one adds its ICP-verified edge to the
revision's graph, rejecting one records the refusal; each is a new revision.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from app.editing.context import EditContext
from app.editing.graph import edge_key, with_loop, without_loop
from app.jobs import Cancel, Progress, Work
from app.workbench import EditError
from slam6d.loops import LoopHypothesis, detect_loops


def hypothesis_dict(h: LoopHypothesis) -> dict[str, Any]:
    """One hypothesis as the review list shows it (and the journal stores it)."""
    return {
        "i": int(h.i),
        "j": int(h.j),
        "distance": float(h.distance),
        "path_length": float(h.path_length),
        "overlap": float(h.overlap),
        "fitness": float(h.fitness),
        "rms": float(h.rms),
        "verified": bool(h.accepted),
        "reason": h.reason,
        "transform": None if h.transform is None else np.asarray(h.transform).tolist(),
    }


def hypotheses_entry(hypotheses: Sequence[LoopHypothesis]) -> dict[str, Any]:
    """Journal parameters of a ``loop_hypotheses`` entry (also written after a registration run)."""
    return {"hypotheses": [hypothesis_dict(h) for h in hypotheses]}


class LoopReview:
    def __init__(self, context: EditContext) -> None:
        self.context = context

    def detect(
        self, session_id: str, progress: Progress | None = None, cancel: Cancel | None = None
    ) -> list[LoopHypothesis]:
        """Loop hypotheses from the current poses, the best per newer scan verified by ICP (the engine's detection)."""
        context = self.context
        return detect_loops(
            context.models(session_id),
            context.poses(session_id),
            context.config(session_id).loop,
            context.config(session_id).max_range,
            progress=None if progress is None else lambda done, total: progress("verifying loops", done, total),
            cancel=cancel,
        )

    def detect_job(self, session_id: str, author: str) -> Work:
        """Detection as a job whose result becomes the review list (a journal entry, no new revision)."""
        self.context.session(session_id)

        def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
            found = self.detect(session_id, progress, cancel)
            self.store(session_id, found, author)
            return {"hypotheses": len(found), "verified": sum(h.accepted for h in found)}

        return work

    def store(self, session_id: str, hypotheses: Sequence[LoopHypothesis], author: str) -> None:
        self.context.session(session_id).journal.append(author, "loop_hypotheses", hypotheses_entry(hypotheses))
        self.context.workbench.notify(session_id)

    def listed(self, session_id: str) -> list[dict[str, Any]]:
        """The latest review list, each with its status in the current revision's graph."""
        session = self.context.session(session_id)
        latest: list[dict[str, Any]] = []
        for entry in reversed(session.journal.entries()):
            if entry.kind == "loop_hypotheses":
                latest = entry.parameters.get("hypotheses", [])
                break
        graph = session.graph()
        accepted = {tuple(edge_key(int(e["i"]), int(e["j"]))) for e in graph.get("loops", [])}
        rejected = {tuple(edge_key(*e)) for e in graph.get("rejected", [])}
        out = []
        for k, hyp in enumerate(latest):
            key = tuple(edge_key(hyp["i"], hyp["j"]))
            status = "accepted" if key in accepted else "rejected" if key in rejected else "pending"
            out.append({"k": k, **hyp, "status": status})
        return out

    def decide(self, session_id: str, k: int, accept: bool, author: str) -> dict[str, Any]:
        """Accept (a loop edge joins the graph) or reject a hypothesis: a new revision of the graph."""
        listed = self.listed(session_id)
        if not 0 <= k < len(listed):
            raise EditError(f"no loop hypothesis {k}; there are {len(listed)}", 404)
        hyp = listed[k]
        wanted = "accepted" if accept else "rejected"
        if hyp["status"] == wanted:
            raise EditError(f"loop {hyp['i']}-{hyp['j']} is already {wanted}")
        graph = self.context.session(session_id).graph()
        if accept:
            edge = {name: hyp[name] for name in ("i", "j", "fitness", "rms", "transform")}
            graph = with_loop(graph, {**edge, "kind": "loop"})
        else:
            graph = without_loop(graph, hyp["i"], hyp["j"])
            graph["rejected"] = [*graph.get("rejected", []), edge_key(hyp["i"], hyp["j"])]
        kind = "accept_loop" if accept else "reject_loop"
        parameters = {"hypothesis": k, "i": hyp["i"], "j": hyp["j"]}
        revision = self.context.commit_graph(session_id, graph, author, kind, parameters)
        return {"revision": revision, "status": wanted, "i": hyp["i"], "j": hyp["j"]}
