"""Editing a session's map by hand and by stage: loops, edges, moves, loop closing, relaxation, guesses.

This is the workbench's non-GUI layer for everything that changes poses or the pose graph after a
run. The REST API and the 3D view's panels both call it, so a button and a request do the same
thing, and every change is one journal entry (with author and parameters) that undo/redo and
every other browser on the session see.

The pose graph of a revision (``Revision.graph``) is a small JSON document::

    {"loops": [{"i", "j", "kind": "loop"|"manual", "fitness", "rms", "transform"}],
     "removed": [[i, j], ...],     # sequential edges deleted by hand
     "rejected": [[i, j], ...]}    # loop hypotheses a person turned down

``transform`` is scan j in scan i's frame as ICP found it; loop closing and relaxation use it.
Loop hypotheses (the review list) are a journal entry of kind ``loop_hypotheses``: finding them
changes nothing, deciding on one is a new revision of the graph.

Guardrails live here, not in the GUI: relaxation refuses a graph whose scans are not all tied to a
fixed scan (the engine's :class:`~slam6d.errors.RelaxationError`), and every edit that moves
scans compares a residual summary before and after and reports a jump as a warning.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from app.jobs import Cancel, JobCancelledError, Progress, Work
from app.registration import hypotheses_entry, pipeline_config
from app.workbench import EditError
from slam6d.errors import RegistrationError, RelaxationError
from slam6d.geometry import Matrix, invert, transform_points
from slam6d.icp import FloatArray, ICPConfig, icp
from slam6d.initial_guess import GuessResult, OctreeSearchConfig, config_for, octree_guess
from slam6d.loops import LoopHypothesis, diffuse_loop_correction, find_loop_hypotheses, loop_correction, verify
from slam6d.lum import match_edge
from slam6d.model import ModelIndex
from slam6d.octree import Octree, reduce_points
from slam6d.pipeline import PipelineConfig
from slam6d.posegraph import check_connected, optimize_pose_graph
from slam6d.relax import NeighbourPair, RelaxationConfig, ScanModels
from slam6d.session import Session
from slam6d.simultaneous import UnionIndex, simultaneous_matching
from slam6d.trace import to_jsonable

# An edit "makes residuals jump" when the summary RMS grows by this factor and by at least this
# many metres, or when the paired fraction of the edges drops by more than RESIDUAL_JUMP_OVERLAP.
RESIDUAL_JUMP_FACTOR = 1.5
RESIDUAL_JUMP_METRES = 0.02
RESIDUAL_JUMP_OVERLAP = 0.15
RELAX_METHODS = ("lum", "simultaneous")


# ---------------------------------------------------------------- residual summary


@dataclass
class ResidualSummary:
    """How well the scans joined by graph edges agree: closest-point RMS and paired fraction."""

    rms: float  # metres, over all pairs of all edges within ``max_distance``
    paired: float  # mean over edges of the fraction of data points with a partner
    edges: list[dict[str, float]]  # per edge: i, j, rms, paired
    max_distance: float

    def as_dict(self) -> dict[str, Any]:
        return to_jsonable(self.__dict__)


def plane_residual(model: ModelIndex, data: FloatArray, max_distance: float) -> float:
    """Upper quartile of the point-to-plane distances of ``data`` (in the model's frame) to ``model``,
    over the points with a partner within ``max_distance``.

    This tells a good edge from a bad one on any scan density: closest-point distances between well
    aligned scans still grow with the point spacing and with the parts that do not overlap (on the
    demo session 0.33 m aligned against 0.38 m at the odometry), while the distance along the
    surface normal stays near the range noise (1 cm there, 6-10 cm at the odometry). The upper
    quartile rather than the median: a scan slid sideways over flat ground keeps its ground points
    on the ground plane, and those can be half of a scan. NaN where no point of ``data`` has a
    partner with a usable normal.
    """
    distances = np.abs(model.plane_residuals(data, max_distance))
    return float(np.percentile(distances, 75)) if len(distances) else float("nan")


def residual_summary(
    models: ScanModels, poses: Sequence[Matrix], edges: Sequence[tuple[int, int]], sample: int = 1500
) -> ResidualSummary:
    """Per edge, scan j's thinned points against scan i's; pairs count within 4x the ICP max distance.

    The wider reach keeps the RMS meaningful after a bad edit: with the ICP distance itself, a scan
    dragged a metre away would simply lose its pairs and its RMS would look no worse.
    """
    reach = 4.0 * models.config.max_distance
    total, count, per_edge = 0.0, 0, []
    for i, j in edges:
        data = transform_points(invert(poses[i]) @ poses[j], models.thinned(j, sample))
        dist, idx = models.index(i).nearest(data, reach)
        ok = idx >= 0
        squares = float(np.sum(dist[ok] ** 2))
        total += squares
        count += int(ok.sum())
        per_edge.append(
            {
                "i": i,
                "j": j,
                "rms": float(np.sqrt(squares / ok.sum())) if ok.any() else float("nan"),
                "paired": float(ok.mean()) if len(ok) else 0.0,
                "plane": plane_residual(models.index(i), data, models.config.max_distance),
            }
        )
    rms = float(np.sqrt(total / count)) if count else float("nan")
    paired = float(np.mean([e["paired"] for e in per_edge])) if per_edge else 0.0
    return ResidualSummary(rms, paired, per_edge, reach)


def residual_jump(before: ResidualSummary, after: ResidualSummary) -> str | None:
    """A warning naming the worst edge when ``after`` is clearly worse than ``before``, else None."""
    worse_rms = (
        np.isfinite(before.rms)
        and np.isfinite(after.rms)
        and after.rms > RESIDUAL_JUMP_FACTOR * before.rms
        and after.rms - before.rms > RESIDUAL_JUMP_METRES
    )
    lost_overlap = before.paired - after.paired > RESIDUAL_JUMP_OVERLAP
    if not (worse_rms or lost_overlap):
        return None
    changes = [
        (a["rms"] - b["rms"] if np.isfinite(a["rms"]) and np.isfinite(b["rms"]) else 0.0, b["paired"] - a["paired"], a)
        for b, a in zip(before.edges, after.edges, strict=True)
    ]
    worst = max(changes, key=lambda c: (c[1] > RESIDUAL_JUMP_OVERLAP, c[0] + c[1]))[2]
    return (
        f"residuals jumped: RMS {before.rms:.3f} m -> {after.rms:.3f} m, paired {before.paired:.0%} -> "
        f"{after.paired:.0%} (worst edge {worst['i']}-{worst['j']}); undo if this was not intended"
    )


# ---------------------------------------------------------------- graph documents


def _pair(i: int, j: int) -> list[int]:
    return [min(i, j), max(i, j)]


def graph_edge_list(count: int, graph: dict[str, Any]) -> list[dict[str, Any]]:
    """The edges of a revision as the user sees them: sequential (unless removed), then loops and manual ones."""
    removed = {tuple(_pair(*e)) for e in graph.get("removed", [])}
    edges: list[dict[str, Any]] = [
        {"i": k, "j": k + 1, "kind": "sequential"} for k in range(count - 1) if (k, k + 1) not in removed
    ]
    for loop in graph.get("loops", []):
        if tuple(_pair(int(loop["i"]), int(loop["j"]))) not in removed:
            edges.append({**loop, "i": int(loop["i"]), "j": int(loop["j"]), "kind": str(loop.get("kind", "loop"))})
    return [{"k": k, **e} for k, e in enumerate(edges)]


def _with_loop(graph: dict[str, Any], edge: dict[str, Any]) -> dict[str, Any]:
    key = _pair(edge["i"], edge["j"])
    loops = [e for e in graph.get("loops", []) if _pair(int(e["i"]), int(e["j"])) != key]
    return {
        **graph,
        "loops": [*loops, edge],
        "removed": [e for e in graph.get("removed", []) if _pair(*e) != key],
        "rejected": [e for e in graph.get("rejected", []) if _pair(*e) != key],
    }


# ---------------------------------------------------------------- the editor


class Editor:
    """Edits of one workbench's sessions; keeps each session's reduced scans (built once) for ICP."""

    def __init__(self, workbench: Any) -> None:
        self.workbench = workbench
        self._models: dict[str, tuple[int, ScanModels]] = {}
        self._guesses: dict[tuple[Any, ...], GuessResult] = {}
        self._lock = threading.Lock()

    # -- shared pieces

    def config(self, session_id: str) -> PipelineConfig:
        return pipeline_config(self.workbench.state(session_id).session.config.engine)

    def icp_config(self, session_id: str) -> ICPConfig:
        # the models are reduced already, as in the pipeline
        return replace(self.config(session_id).icp, data_voxel_size=0.0)

    def models(self, session_id: str) -> ScanModels:
        """Each scan reduced to the engine's voxel size, with kd-trees built on first use."""
        sequence = self.workbench.state(session_id).sequence()
        with self._lock:
            cached = self._models.get(session_id)
            if cached is not None and cached[0] == id(sequence):
                return cached[1]
            voxel = float(self.config(session_id).voxel_size)
            reduced = [s.points[reduce_points(s.points, voxel)] if voxel > 0 else s.points for s in sequence.scans]
            models = ScanModels(reduced, self.icp_config(session_id))
            self._models[session_id] = (id(sequence), models)
            return models

    def _session(self, session_id: str) -> Session:
        return self.workbench.state(session_id).session

    def _check_scan(self, session_id: str, *indices: int) -> int:
        count = len(self.workbench.current_poses(session_id))
        for k in indices:
            if not 0 <= k < count:
                raise EditError(f"no scan {k}; the session has scans 0..{count - 1}", 404)
        return count

    def edges(self, session_id: str, graph: dict[str, Any] | None = None) -> list[dict[str, Any]]:
        count = len(self.workbench.current_poses(session_id))
        return graph_edge_list(count, self._session(session_id).graph() if graph is None else graph)

    def residuals(
        self, session_id: str, poses: Sequence[Matrix] | None = None, graph: dict[str, Any] | None = None
    ) -> ResidualSummary:
        poses = self.workbench.current_poses(session_id) if poses is None else poses
        pairs = [(e["i"], e["j"]) for e in self.edges(session_id, graph)]
        return residual_summary(self.models(session_id), poses, pairs)

    def commit_checked(
        self,
        session_id: str,
        poses: Sequence[Matrix],
        author: str,
        kind: str,
        parameters: dict[str, Any],
        graph: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Commit new poses with the residual summary before and after; a jump becomes ``warning``."""
        before = self.residuals(session_id)
        after = self.residuals(session_id, poses, graph)
        warning = residual_jump(before, after)
        params = {**parameters, "residual_before": before.rms, "residual_after": after.rms}
        if warning:
            params["warning"] = warning
        revision = self.workbench.commit(session_id, list(poses), author, kind, params, graph=graph)
        return {
            "revision": revision,
            "residual_before": before.as_dict(),
            "residual_after": after.as_dict(),
            "warning": warning,
        }

    # -- loop hypotheses

    def detect_loops(self, session_id: str, progress: Progress | None = None, cancel: Cancel | None = None) -> list:
        """Loop hypotheses from the current poses, the best per newer scan verified by ICP."""
        config = self.config(session_id)
        models = self.models(session_id)
        poses = self.workbench.current_poses(session_id)
        cube = config.loop.overlap_cube
        occupancies: dict[int, Any] = {}

        def occupancy(k: int) -> Any:
            if k not in occupancies:
                occupancies[k] = Octree(models.points[k], cube).occupancy(cube)
            return occupancies[k]

        # the laser's reach, estimated as the pipeline does when not configured: a typical scan's extent
        max_range = config.max_range or float(np.median([models.extent(k) for k in range(len(models))]))
        candidates = find_loop_hypotheses(poses, max_range, config.loop, occupancy, models.points)
        best: dict[int, LoopHypothesis] = {}
        for hyp in candidates:  # sorted best first per newer scan
            best.setdefault(hyp.j, hyp)
        chosen = [best[j] for j in sorted(best)]
        verified = []
        for n, hyp in enumerate(chosen):
            if cancel is not None and cancel():
                raise JobCancelledError()
            verified.append(verify(hyp, models.index(hyp.i), models.points[hyp.j], models.config, config.loop))
            if progress is not None:
                progress("verifying loops", n + 1, len(chosen))
        return verified

    def detect_loops_job(self, session_id: str, author: str) -> Work:
        """Detection as a job whose result becomes the review list (a journal entry, no new revision)."""
        self._session(session_id)

        def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
            found = self.detect_loops(session_id, progress, cancel)
            self.store_hypotheses(session_id, found, author)
            return {"hypotheses": len(found), "verified": sum(h.accepted for h in found)}

        return work

    def store_hypotheses(self, session_id: str, hypotheses: Sequence[LoopHypothesis], author: str) -> None:
        self._session(session_id).journal.append(author, "loop_hypotheses", hypotheses_entry(hypotheses))
        self.workbench.notify(session_id)

    def hypotheses(self, session_id: str) -> list[dict[str, Any]]:
        """The latest review list, each with its status in the current revision's graph."""
        session = self._session(session_id)
        latest: list[dict[str, Any]] = []
        for entry in reversed(session.journal.entries()):
            if entry.kind == "loop_hypotheses":
                latest = entry.parameters.get("hypotheses", [])
                break
        graph = session.graph()
        accepted = {tuple(_pair(int(e["i"]), int(e["j"]))) for e in graph.get("loops", [])}
        rejected = {tuple(_pair(*e)) for e in graph.get("rejected", [])}
        out = []
        for k, hyp in enumerate(latest):
            key = tuple(_pair(hyp["i"], hyp["j"]))
            status = "accepted" if key in accepted else "rejected" if key in rejected else "pending"
            out.append({"k": k, **hyp, "status": status})
        return out

    def decide_loop(self, session_id: str, k: int, accept: bool, author: str) -> dict[str, Any]:
        """Accept (a loop edge joins the graph) or reject a hypothesis: a new revision of the graph."""
        listed = self.hypotheses(session_id)
        if not 0 <= k < len(listed):
            raise EditError(f"no loop hypothesis {k}; there are {len(listed)}", 404)
        hyp = listed[k]
        wanted = "accepted" if accept else "rejected"
        if hyp["status"] == wanted:
            raise EditError(f"loop {hyp['i']}-{hyp['j']} is already {wanted}")
        graph = self._session(session_id).graph()
        key = _pair(hyp["i"], hyp["j"])
        if accept:
            edge = {k2: hyp[k2] for k2 in ("i", "j", "fitness", "rms", "transform")}
            graph = _with_loop(graph, {**edge, "kind": "loop"})
        else:
            graph = {
                **graph,
                "loops": [e for e in graph.get("loops", []) if _pair(int(e["i"]), int(e["j"])) != key],
                "rejected": [*graph.get("rejected", []), key],
            }
        poses = self.workbench.current_poses(session_id)
        kind = "accept_loop" if accept else "reject_loop"
        revision = self.workbench.commit(
            session_id, poses, author, kind, {"hypothesis": k, "i": hyp["i"], "j": hyp["j"]}, graph=graph
        )
        return {"revision": revision, "status": wanted, "i": hyp["i"], "j": hyp["j"]}

    # -- edges by hand

    def add_edge(self, session_id: str, i: int, j: int, author: str, force: bool = False) -> dict[str, Any]:
        """A loop edge between two scans, refined by ICP from their current relative pose."""
        self._check_scan(session_id, i, j)
        if i == j:
            raise EditError("an edge needs two different scans", 422)
        i, j = _pair(i, j)
        poses = self.workbench.current_poses(session_id)
        models = self.models(session_id)
        hyp = LoopHypothesis(i, j, float(np.linalg.norm(poses[i][:3, 3] - poses[j][:3, 3])), 0.0)
        hyp.transform = invert(poses[i]) @ poses[j]
        verdict = verify(hyp, models.index(i), models.points[j], models.config, self.config(session_id).loop)
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
        graph = _with_loop(self._session(session_id).graph(), edge)
        parameters = {"i": i, "j": j, "fitness": edge["fitness"], "rms": edge["rms"], "forced": bool(force)}
        revision = self.workbench.commit(session_id, poses, author, "add_edge", parameters, graph=graph)
        return {"revision": revision, "edge": edge, "warning": None if verdict.accepted else verdict.reason}

    def delete_edge(self, session_id: str, k: int, author: str) -> dict[str, Any]:
        graph = self._session(session_id).graph()
        listed = self.edges(session_id, graph)
        if not 0 <= k < len(listed):
            raise EditError(f"no edge {k}; there are {len(listed)}", 404)
        edge = listed[k]
        key = _pair(edge["i"], edge["j"])
        if edge["kind"] == "sequential":
            graph = {**graph, "removed": [*graph.get("removed", []), key]}
        else:
            graph = {**graph, "loops": [e for e in graph.get("loops", []) if _pair(int(e["i"]), int(e["j"])) != key]}
        poses = self.workbench.current_poses(session_id)
        params = {"edge": k, "i": edge["i"], "j": edge["j"], "kind": edge["kind"]}
        revision = self.workbench.commit(session_id, poses, author, "delete_edge", params, graph=graph)
        return {"revision": revision, "deleted": {key: edge[key] for key in ("i", "j", "kind")}}

    # -- moving a scan

    def move_scan(self, session_id: str, k: int, pose: Matrix, author: str, refine: bool = False) -> dict[str, Any]:
        """Place scan k (a drag of the gizmo); with ``refine`` ICP continues from there against its neighbours."""
        self._check_scan(session_id, k)
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise EditError("pose must be a finite 4x4 matrix", 422)
        poses = self.workbench.current_poses(session_id)
        params: dict[str, Any] = {"scan": k, "pose": pose, "refine": refine}
        if refine:
            neighbours = sorted(
                {e["j"] if e["i"] == k else e["i"] for e in self.edges(session_id) if k in (e["i"], e["j"])}
            )
            if not neighbours:
                raise EditError(f"scan {k} has no edges to refine against")
            models = self.models(session_id)
            try:
                result = icp(UnionIndex(models, neighbours, poses), models.points[k], pose, models.config)
            except RegistrationError as exc:
                raise EditError(f"ICP from the new place failed: {exc}", 422) from None
            pose = result.transform
            params.update(neighbours=neighbours, fitness=result.fitness, rms=result.rms)
        poses[k] = pose
        return self.commit_checked(session_id, poses, author, "icp_move" if refine else "manual_move", params)

    # -- loop closing and relaxation (background jobs)

    def close_loops_job(self, session_id: str, author: str) -> Work:
        """Error diffusion over every loop edge that carries an ICP transform, oldest loop end first."""
        loops = [e for e in self.edges(session_id) if e["kind"] != "sequential" and e.get("transform") is not None]
        if not loops:
            raise EditError("there is no accepted loop or manual edge with an ICP transform to close")
        loops.sort(key=lambda e: (e["j"], e["i"]))

        def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
            poses = self.workbench.current_poses(session_id)
            before = [p.copy() for p in poses]
            for n, edge in enumerate(loops):
                if cancel():
                    raise JobCancelledError()
                hyp = LoopHypothesis(edge["i"], edge["j"], 0.0, 0.0, transform=np.asarray(edge["transform"]))
                poses = diffuse_loop_correction(poses, hyp.i, hyp.j, loop_correction(poses, hyp))
                progress("closing loops", n + 1, len(loops))
            params = {"loops": [[e["i"], e["j"]] for e in loops], "displacement": displacements(before, poses)}
            return self.commit_checked(session_id, poses, author, "close_loops", params)

        return work

    def check_relaxable(self, session_id: str, fixed: Sequence[int]) -> list[dict[str, Any]]:
        """The graph's edges if relaxation can run; else RelaxationError / EditError with the reason."""
        count = self._check_scan(session_id, *fixed)
        if not fixed:
            raise EditError("no fixed scan: relaxation needs at least one scan held in place (usually scan 0)")
        edges = self.edges(session_id)
        check_connected(count, [(e["i"], e["j"]) for e in edges], fixed)
        return edges

    def relax_job(self, session_id: str, author: str, method: str = "lum", fixed: Sequence[int] = (0,)) -> Work:
        """Simultaneous matching (the engine's, over overlapping scans) or LUM over this session's graph."""
        if method not in RELAX_METHODS:
            raise EditError(f"unknown relaxation '{method}'; known: {', '.join(RELAX_METHODS)}", 422)
        edges = self.check_relaxable(session_id, fixed)
        relax_config = self.config(session_id).relax

        def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
            models = self.models(session_id)
            poses = self.workbench.current_poses(session_id)
            if method == "simultaneous":
                result = simultaneous_matching(
                    models,
                    poses,
                    fixed=fixed,
                    config=relax_config,
                    progress=lambda it, _r, _m: progress("simultaneous matching", it, it + 1),
                    cancel=cancel,
                )
                relaxed, info = result.poses, {"iterations": result.iterations}
            else:
                relaxed, info = graph_lum(models, poses, edges, fixed, relax_config, progress, cancel)
            params = {"method": method, "fixed": list(fixed), **info, "displacement": displacements(poses, relaxed)}
            return self.commit_checked(session_id, relaxed, author, f"relax_{method}", params)

        return work

    # -- octree guesses

    def guess(self, session_id: str, data: int, model: int | None = None) -> tuple[GuessResult, int, int]:
        """The octree search for scan ``data`` against ``model`` (default the previous scan), from the current poses.

        Cached per revision: the search is deterministic, so listing and applying see the same candidates.
        """
        model = data - 1 if model is None else model
        self._check_scan(session_id, data, model)
        if data == model:
            raise EditError("the guess needs two different scans", 422)
        revision = self._session(session_id).revision
        key = (session_id, revision, model, data)
        with self._lock:
            found = self._guesses.get(key)
        if found is None:
            models = self.models(session_id)
            poses = self.workbench.current_poses(session_id)
            found = octree_guess(models.points[model], models.points[data], invert(poses[model]) @ poses[data])
            with self._lock:
                self._guesses = {k: v for k, v in self._guesses.items() if k[0] != session_id or k[1] == revision}
                self._guesses[key] = found
        return found, model, data

    def search_config(self, session_id: str) -> OctreeSearchConfig:
        models = self.models(session_id)
        return config_for(models.points[0])

    def guess_summary(
        self, session_id: str, data: int, model: int | None = None, level: int = -1, top: int = 10
    ) -> dict[str, Any]:
        """Candidates of one search level, best first, with the world pose each would give the data scan."""
        result, model, data = self.guess(session_id, data, model)
        if not -len(result.levels) <= level < len(result.levels):
            raise EditError(f"no search level {level}; the search has {len(result.levels)}", 422)
        chosen = result.levels[level]
        models = self.models(session_id)
        world_model = self.workbench.current_poses(session_id)[model]
        tree_model = Octree(models.points[model], chosen.cube_size)
        tree_data = Octree(models.points[data], chosen.cube_size)
        candidates = []
        for rank, cand in enumerate(chosen.candidates.best(top)):
            candidates.append(
                {
                    "rank": rank,
                    "score": int(cand.score),
                    "fraction": cand.score / max(chosen.data_points, 1),
                    "offsets": list(cand.offsets),
                    "transform": cand.transform.tolist(),
                    "pose": (world_model @ cand.transform).tolist(),
                    "winner": bool(np.allclose(cand.transform, chosen.winner.transform)),
                }
            )
        return {
            "model": model,
            "data": data,
            "level": level % len(result.levels),
            "levels": [lv.cube_size for lv in result.levels],
            "cube_size": chosen.cube_size,
            "model_cubes": len(tree_model.occupancy(chosen.cube_size)),
            "data_cubes": len(tree_data.occupancy(chosen.cube_size)),
            "data_points": chosen.data_points,
            "evaluated": len(chosen.candidates),
            "score": int(result.score),
            "candidates": candidates,
        }

    def occupied_cubes(self, session_id: str, scan: int, cube_size: float) -> np.ndarray:
        """Centres of a scan's occupied cubes in its own frame (for drawing)."""
        return Octree(self.models(session_id).points[scan], cube_size).occupied_cubes(cube_size)

    def apply_candidate(
        self, session_id: str, data: int, model: int | None, rank: int, author: str, level: int = -1
    ) -> dict[str, Any]:
        """ICP from a chosen candidate of the search; the data scan moves where ICP ends."""
        summary = self.guess_summary(session_id, data, model, level, top=max(rank + 1, 1))
        if not 0 <= rank < len(summary["candidates"]):
            raise EditError(f"no candidate {rank}", 404)
        cand = summary["candidates"][rank]
        model, data = summary["model"], summary["data"]
        models = self.models(session_id)
        try:
            result = icp(models.index(model), models.points[data], np.asarray(cand["transform"]), models.config)
        except RegistrationError as exc:
            raise EditError(f"ICP from candidate {rank} failed: {exc}", 422) from None
        poses = self.workbench.current_poses(session_id)
        poses[data] = poses[model] @ result.transform
        params = {
            "model": model,
            "data": data,
            "candidate": rank,
            "level": summary["level"],
            "score": cand["score"],
            "fitness": result.fitness,
            "rms": result.rms,
        }
        outcome = self.commit_checked(session_id, poses, author, "icp_from_candidate", params)
        return {**outcome, "fitness": result.fitness, "rms": result.rms}


def graph_lum(
    models: ScanModels,
    poses: Sequence[Matrix],
    edges: Sequence[dict[str, Any]],
    fixed: Sequence[int],
    config: RelaxationConfig,
    progress: Progress,
    cancel: Cancel,
) -> tuple[list[Matrix], dict[str, Any]]:
    """LUM over the session's own graph (sequential, loop and manual edges, minus deleted ones).

    Each edge is matched by ICP (starting, in the first round, from a loop's stored transform, so
    the loop's drift is what the solve distributes), then all poses are solved at once; rounds
    repeat from the new poses until no scan moves more than ``config.tolerance``.
    """
    current = [np.array(p) for p in poses]
    chi2: list[float] = []
    rounds = 0
    total = config.max_rounds * len(edges)
    for rounds in range(1, config.max_rounds + 1):
        measured = []
        for n, edge in enumerate(edges):
            if cancel():
                raise JobCancelledError()
            i, j = edge["i"], edge["j"]
            placed = list(current)
            if rounds == 1 and edge.get("transform") is not None:
                placed[j] = current[i] @ np.asarray(edge["transform"])
            try:
                measured.append(match_edge(models, placed, NeighbourPair(i, j, 0), config))
            except RegistrationError as exc:
                raise RelaxationError(f"LUM: scans {i} and {j} no longer match: {exc}") from exc
            progress("LUM: matching edges", (rounds - 1) * len(edges) + n + 1, total)
        result = optimize_pose_graph(current, measured, fixed=fixed, max_iterations=20)
        if not result.converged and not np.isfinite(result.residual_after):
            raise RelaxationError("the pose-graph solver did not converge")
        chi2.append(result.residual_after)
        moved = max(float(np.linalg.norm(a[:3, 3] - b[:3, 3])) for a, b in zip(result.poses, current, strict=True))
        current = result.poses
        if moved <= config.tolerance:
            break
    return current, {"rounds": rounds, "chi2": chi2}


def displacements(before: Sequence[Matrix], after: Sequence[Matrix]) -> list[float]:
    """How far each scan's origin moved (metres): the before/after colouring of the 3D view."""
    return [
        float(np.linalg.norm(np.asarray(a)[:3, 3] - np.asarray(b)[:3, 3])) for b, a in zip(before, after, strict=True)
    ]


_editors: weakref.WeakKeyDictionary[Any, Editor] = weakref.WeakKeyDictionary()
_editors_lock = threading.Lock()


def editor_for(workbench: Any) -> Editor:
    """The one editor of a workbench (shared by the REST API and the 3D views)."""
    with _editors_lock:
        editor = _editors.get(workbench)
        if editor is None:
            editor = _editors[workbench] = Editor(workbench)
        return editor


__all__ = [
    "Editor",
    "ResidualSummary",
    "displacements",
    "editor_for",
    "graph_edge_list",
    "graph_lum",
    "residual_jump",
    "residual_summary",
]
