"""Octree guesses for one pair of scans: the ranked candidates of each search level, ICP from a chosen one."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.editing.context import EditContext
from app.workbench import EditError
from slam6d.errors import RegistrationError
from slam6d.geometry import invert
from slam6d.icp import icp
from slam6d.initial_guess import GuessResult, octree_guess
from slam6d.octree import Octree


class OctreeGuesses:
    def __init__(self, context: EditContext) -> None:
        self.context = context
        self._found: dict[tuple[Any, ...], GuessResult] = {}

    def search(self, session_id: str, data: int, model: int | None = None) -> tuple[GuessResult, int, int]:
        """The octree search for scan ``data`` against ``model`` (default the previous scan), from the current poses.

        Cached per revision: the search is deterministic, so listing and applying see the same candidates.
        """
        context = self.context
        model = data - 1 if model is None else model
        context.check_scan(session_id, data, model)
        if data == model:
            raise EditError("the guess needs two different scans", 422)
        revision = context.session(session_id).revision
        key = (session_id, revision, model, data)
        with context.lock:
            found = self._found.get(key)
        if found is None:
            models = context.models(session_id)
            poses = context.poses(session_id)
            found = octree_guess(models.points[model], models.points[data], invert(poses[model]) @ poses[data])
            with context.lock:
                self._found = {k: v for k, v in self._found.items() if k[0] != session_id or k[1] == revision}
                self._found[key] = found
        return found, model, data

    def summary(
        self, session_id: str, data: int, model: int | None = None, level: int = -1, top: int = 10
    ) -> dict[str, Any]:
        """Candidates of one search level, best first, with the world pose each would give the data scan."""
        result, model, data = self.search(session_id, data, model)
        if not -len(result.levels) <= level < len(result.levels):
            raise EditError(f"no search level {level}; the search has {len(result.levels)}", 422)
        chosen = result.levels[level]
        models = self.context.models(session_id)
        world_model = self.context.poses(session_id)[model]
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
        return Octree(self.context.models(session_id).points[scan], cube_size).occupied_cubes(cube_size)

    def apply(
        self, session_id: str, data: int, model: int | None, rank: int, author: str, level: int = -1
    ) -> dict[str, Any]:
        """ICP from a chosen candidate of the search; the data scan moves where ICP ends."""
        summary = self.summary(session_id, data, model, level, top=max(rank + 1, 1))
        if not 0 <= rank < len(summary["candidates"]):
            raise EditError(f"no candidate {rank}", 404)
        cand = summary["candidates"][rank]
        model, data = summary["model"], summary["data"]
        models = self.context.models(session_id)
        try:
            result = icp(models.index(model), models.points[data], np.asarray(cand["transform"]), models.config)
        except RegistrationError as exc:
            raise EditError(f"ICP from candidate {rank} failed: {exc}", 422) from None
        poses = self.context.poses(session_id)
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
        outcome = self.context.commit_checked(session_id, poses, author, "icp_from_candidate", params)
        return {**outcome, "fitness": result.fitness, "rms": result.rms}
