"""Running the engine's registration pipeline for a session, as a job or step by step.

Engine parameters come from ``[engine]`` in session.toml, overridden per run; unknown names are
refused (a typo must not silently run with defaults). The pipeline works on its own copy of the
scans so the 3D view keeps showing the committed revision until the run is stored.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from app.jobs import Cancel, Progress, Work
from slam6d import pipeline
from slam6d.loops import LoopHypothesis
from slam6d.scan import Scan, ScanSequence
from slam6d.trace import to_jsonable


def _build(cls: type, values: dict[str, Any], what: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ValueError(f"unknown {what} parameter(s): {', '.join(unknown)}; known: {', '.join(sorted(fields))}")
    kwargs = {}
    for name, value in values.items():
        default = getattr(cls(), name)
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = _build(type(default), value, f"{what}.{name}")
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def pipeline_config(engine: dict[str, Any], overrides: dict[str, Any] | None = None) -> pipeline.PipelineConfig:
    """PipelineConfig from session parameters; ``icp.*`` keys may be given flat as ``icp_<name>`` too.

    ``display_*`` keys belong to the 3D view (e.g. ``display_voxel_size``) and are skipped here.
    """
    values: dict[str, Any] = {}
    for source in (engine, overrides or {}):
        for key, value in source.items():
            if key.startswith("display_"):  # settings of the 3D view, not of the engine
                continue
            if key.startswith("icp_"):
                values.setdefault("icp", {})[key[4:]] = value
            elif key == "icp" and isinstance(value, dict):
                values.setdefault("icp", {}).update(value)
            else:
                values[key] = value
    return _build(pipeline.PipelineConfig, values, "pipeline")


def working_copy(sequence: ScanSequence) -> ScanSequence:
    """Scans sharing the (read-only) point arrays but with their own poses."""
    scans = [
        Scan(s.points, s.pose.copy(), name=s.name, source=s.source, intensity=s.intensity, has_pose=s.has_pose)
        for s in sequence.scans
    ]
    return ScanSequence(scans, sequence.convention, sequence.source, sequence.format_name)


def accepted_loops(report: Any) -> list[dict[str, Any]]:
    loops = getattr(report, "loops", None) or []
    return [
        {
            "i": int(h.i),
            "j": int(h.j),
            "kind": "loop",
            "fitness": float(getattr(h, "fitness", 0.0)),
            "rms": to_jsonable(float(getattr(h, "rms", float("nan")))),
            "transform": to_jsonable(getattr(h, "transform", None)),
        }
        for h in loops
        if getattr(h, "accepted", True)
    ]


def registration_job(workbench: Any, session_id: str, author: str, parameters: dict[str, Any]) -> Work:
    """A job that runs the whole pipeline and commits its poses as a new revision."""
    state = workbench.state(session_id)
    config = pipeline_config(state.session.config.engine, parameters)

    def work(progress: Progress, cancel: Cancel) -> dict[str, Any]:
        from app.traces import TraceRecorder

        sequence = working_copy(state.sequence(lambda d, t: progress("reading scans", d, t)))
        runner = pipeline.Pipeline(sequence, config)
        recorder = TraceRecorder()
        report = recorder.attach(runner).run(progress, cancel)
        summary = to_jsonable(report)
        return store_run(workbench, session_id, author, runner, recorder, {"config": to_jsonable(config)}) | {
            "report": summary
        }

    return work


def store_run(workbench: Any, session_id: str, author: str, runner: Any, recorder: Any, parameters: dict) -> dict:
    """Commit a finished run with its trace file named in the journal, then its loops for review."""

    session = workbench.state(session_id).session
    meta = {"author": author, "final_poses": to_jsonable(runner.poses)}
    name = recorder.save(session, runner.odometry, meta)
    graph = {"loops": accepted_loops(runner.report), "removed": []}
    revision = workbench.commit(
        session_id, runner.poses, author, "register", {**parameters, "trace": name}, graph=graph
    )
    if runner.report.loops:
        session.journal.append(author, "loop_hypotheses", hypotheses_entry(runner.report.loops))
        workbench.notify(session_id)
    return {"revision": revision, "trace": name}


def _hypothesis_dict(h: LoopHypothesis) -> dict[str, Any]:
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
    return {"hypotheses": [_hypothesis_dict(h) for h in hypotheses]}
